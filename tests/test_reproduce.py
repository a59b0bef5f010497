"""The source's experiments at their scale (`experiments/reproduce.py`), at toy size on the CPU:
every stage runs, stops at its deadline with its agents' states saved, resumes from them, and
leaves data files with the settings the figures are drawn from."""

import json

import pytest

from experiments import reproduce


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
        assert len(r["returns"]) == toy[name].steps // r["horizon"]
    assert len(groups["fig8"]["entropy"]) == toy["fig8"].steps
    for name, of in reproduce.UNROLLS.items():
        r = json.loads((data / f"{name}.json").read_text())
        assert r["of"] == of and len(r["unrolls"]) == 2
        for u in r["unrolls"]:
            assert len(u["bodies"]) == len(u["actions"]) + 1
            for b in u["bodies"]:
                assert b["ci95"][0] <= b["mean"] <= b["ci95"][1] and b["controllers"] == 2
    assert len(groups["compare_random"]["returned"]) == 2
    for figure in ("fig5_unroll", "fig7_unroll", "fig8_a2c_constructor", "compare_constructor",
                   "fig6_ddqn_hidden"):
        assert (out / f"{figure}.png").exists()
