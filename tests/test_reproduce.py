"""The source's experiments at their scale (`experiments/reproduce.py`), at toy size on the CPU:
every stage runs, stops at its deadline with its agents' states saved, resumes from them, and
leaves data files with the settings the figures are drawn from."""

import argparse
import json
from pathlib import Path

import jax
import numpy as np
import pytest

from evojax_morph.spaces import make_space
from experiments import compare_table, reproduce


@pytest.mark.slow
def test_every_stage_resumes_and_leaves_its_data(tmp_path):
    data, out = tmp_path / "data", tmp_path / "fig"
    args = ["--toy", "--data", str(data), "--out", str(out)]
    # a deadline already past: the group builds, evaluates m0, saves its state and stops
    reproduce.main(args + ["--stages", "fig6_h100", "fig5", "--budget", "0"])
    assert (data / "fig6_h100.state").exists() and not (data / "fig6_h100.json").exists()
    assert not (data / "fig5.json").exists()  # its agents are not trained yet
    # every stage's code at its smallest: one width of Figure 6 (the other differs in a
    # number), one group of the comparison (the others differ in the agent)
    ran = ["fig6_h100", "fig8", "compare_random"]
    reproduce.main(args + ["--stages", *ran, "fig5", "fig7", "--budget", "1e6", "--draw"])
    assert not (data / "fig6_h20.json").exists()
    groups = {name: json.loads((data / f"{name}.json").read_text()) for name in ran}
    toy = {name: reproduce.toy(g) for name, g in reproduce.GROUPS.items()}
    for name, r in groups.items():
        assert r["evaluations_per_run"] == toy[name].num_envs * toy[name].steps
        assert r["fitness"] == {"kind": "ppo", "train_steps": 320, "controllers": 1,
                                "inheritance": True}
        assert r["seeds"] == 2 and r["device"] and r["revision"] and r["device_seconds"] > 0
        assert r["task"] == "distance"  # the source's, as the shipped figures
        assert len(r["returns"]) == toy[name].steps // r["horizon"]
    assert len(groups["fig8"]["entropy"]) == toy["fig8"].steps
    for name, of in reproduce.UNROLLS.items():
        r = json.loads((data / f"{name}.json").read_text())
        assert r["of"] == of and len(r["unrolls"]) == 2
        for u in r["unrolls"]:
            assert len(u["bodies"]) == len(u["actions"]) + 1
            for b in u["bodies"]:
                assert b["ci95"][0] <= b["mean"] <= b["ci95"][1] and b["controllers"] == 2
                assert 0 <= b["upright"] <= 1 and abs(b["distance"]) < 10  # the gait, confirmed
    assert len(groups["compare_random"]["returned"]) == 2
    # the comparison's name says the toy's budget of 320 PPO steps, not the task's
    for figure in ("fig5_unroll", "fig7_unroll", "fig8_a2c_constructor", "compare_constructor_320",
                   "fig6_ddqn_hidden"):
        assert (out / f"{figure}.png").exists()


def test_the_comparison_draws_each_agent_and_each_difference_with_its_interval(tmp_path):
    """The comparison's summary, checked by hand: per agent the mean over seeds of the returned
    bodies' confirmed fitness with a t-interval; each agent minus evolution and minus random
    with a Welch t-interval."""
    confirmed = {"a2c": [19.0, 23.0, 18.0], "ddqn": [16.0, 23.0, 17.0],
                 "evolution": [6.0, 15.0, 26.0], "random": [21.0, 18.0, 15.0]}
    for agent, values in confirmed.items():
        returned = [{"body": "b", "mean": v, "ci95": [v - 1, v + 1], "controllers": 2}
                    for v in values]
        (tmp_path / f"compare_{agent}.json").write_text(json.dumps(
            {"evaluations_per_run": 8, "returned": returned, "returned_draw": [100.0] * 3}))
    reproduce.draw(tmp_path, tmp_path / "fig")
    assert (tmp_path / "fig" / "compare_constructor.png").exists()
    # data of another budget than the task's are drawn under a name that says it
    for steps, name in ((20_000, "compare_constructor_20k"), (320, "compare_constructor_320")):
        for path in tmp_path.glob("compare_*.json"):
            path.write_text(json.dumps({**json.loads(path.read_text()),
                                        "fitness": {"train_steps": steps}}))
        reproduce.draw(tmp_path, tmp_path / "fig")
        assert (tmp_path / "fig" / f"{name}.png").exists()
    summary = json.loads((tmp_path / "fig" / "compare_constructor.json").read_text())
    agents, differences = summary["effects"]["agents"], summary["effects"]["differences"]
    assert set(summary["runs"]) == set(confirmed) == set(agents)
    # random: mean 18, sd 3 over 3 seeds, t_{.975, 2} = 4.3027: 18 -/+ 4.3027 x 3 / sqrt(3)
    assert agents["random"]["mean"] == pytest.approx(18.0)
    assert agents["random"]["ci95"] == pytest.approx([18 - 7.4524, 18 + 7.4524], abs=1e-3)
    assert agents["evolution"]["returned_draw"] == [100.0] * 3
    assert set(differences) == {"a2c - evolution", "ddqn - evolution", "random - evolution",
                                "a2c - random", "ddqn - random"}
    # a2c - random: 20 - 18; variances 7 and 9, se = sqrt(7/3 + 9/3) = 2.3094; Welch's
    # df = (16/3)^2 / ((7/3)^2 / 2 + 3^2 / 2) = 3.9385, t_{.975, 3.9385} = 2.7936
    d = differences["a2c - random"]
    assert d["difference"] == pytest.approx(2.0) and d["df"] == pytest.approx(3.9385, abs=1e-4)
    assert d["ci95"] == pytest.approx([2 - 6.4516, 2 + 6.4516], abs=1e-3)
    # together over the 5 pairs (Bonferroni): each at 99%, t_{.995, 3.9385} = 4.6536
    assert d["ci95_simultaneous"] == pytest.approx([2 - 10.7469, 2 + 10.7469], abs=1e-3)
    # Holm: the i-th smallest of the 5 p values times 5 - i, never below the one before
    ps = sorted(e["p"] for e in differences.values())
    holm = np.maximum.accumulate([min(1.0, (5 - i) * p) for i, p in enumerate(ps)])
    assert sorted(e["p_holm"] for e in differences.values()) == pytest.approx(holm)


def test_an_unroll_is_rebuilt_from_its_recorded_mutations():
    """The bodies Figures 5 and 7 draw: the recorded unroll's mutations replayed from m0 give,
    step by step, the bodies the data file names; a record that disagrees is refused."""
    space = make_space("constructor")
    unroll = json.loads(Path("docs/figures/reproduce/fig7.json").read_text())["unrolls"][2]
    bodies = reproduce.unroll_bodies(space, unroll)
    assert [space.canonical(m) for m in bodies] == [b["body"] for b in unroll["bodies"]]
    wrong = {**unroll, "actions": ["node 0: add_leg_end"] + unroll["actions"][1:]}
    with pytest.raises(ValueError, match="not the recorded"):
        reproduce.unroll_bodies(space, wrong)


def test_every_run_confirms_with_keys_of_its_own():
    """Issue 60: no two groups of `reproduce` (each body of a group takes its own splits), and no
    two runs of `compare_table` (method, K, budget, seed), share a confirming key."""
    names = [*reproduce.GROUPS, *reproduce.UNROLLS]
    keys = {tuple(np.asarray(jax.random.key_data(reproduce.group_key(11, n))).ravel())
            for n in names}
    assert len(keys) == len(names)
    runs = [compare_table.confirm_keys(m, k, e, 50) for m in ("evolution", "random")
            for k in (1, 4) for e in (2_000, 10_000)]
    assert len({tuple(np.asarray(key).ravel()) for ks in runs for key in ks}) == 8 * 50


def test_the_walking_comparison_gives_every_method_10_seeds_of_equal_evaluations():
    """The walking task's comparison (issues 44, 60): every method, the regularized evolution
    too, at least 10 seeds a method, the same evaluations a run for every method, whole
    episodes of the Constructor's horizon."""
    walk = reproduce.groups(argparse.Namespace(task="walk", toy=False, space="constructor",
                                               episodes=2))
    compare = [g for name, g in walk.items() if name.startswith("compare_")]
    assert {g.agent for g in compare} == {"a2c", "ddqn", "evolution", "regularized_evolution",
                                          "random"}
    assert all(g.seeds >= 10 for g in compare)
    assert len({g.num_envs * g.steps for g in compare}) == 1
    horizon = make_space("constructor").horizon
    assert all(g.steps % horizon == 0 and g.space == "constructor" for g in compare)
    # the source's groups stay as they were under the distance task
    source = argparse.Namespace(task="distance", toy=False, space="constructor", episodes=2)
    assert reproduce.groups(source) == reproduce.GROUPS
    # on the Crawler (issue 47) the comparison alone moves there: 5 seeds of --episodes whole
    # episodes
    crawler = reproduce.groups(argparse.Namespace(task="walk", toy=False, space="crawler",
                                                  episodes=2))
    moved = [g for name, g in crawler.items() if name.startswith("compare_")]
    assert len(moved) == 5 and all(g.space == "crawler" and g.seeds == 5 for g in moved)
    assert all(g.steps == 2 * make_space("crawler").default_horizon for g in moved)
    assert crawler["fig8"] == reproduce.GROUPS["fig8"]
