"""The table fitness and its builder: rows found by signature, draws, the missing-body errors,
one trace, resumable builds and `run --fitness table`. Tables here are synthetic or of the
predefined fitness (cheap); the real ones hold PPO results built on a GPU."""

import dataclasses
import json
import re

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_spaces import reachable_batched

import evojax_morph as em
from evojax_morph.fitnesses import get_fitness
from evojax_morph.fitnesses import table as tb
from evojax_morph.run import cli
from experiments import build_tables

SEEDS = 6  # results per body of the synthetic table


@pytest.fixture(scope="module")
def walker():
    space = em.make_space("bad_walker")
    bodies, _ = space.enumerate_bodies()
    return space, bodies, [space.canonical(m) for m in bodies]


def synthetic(walker, path, drop=None, nan=False):
    """A table whose result s of row r is 1000 r + 2^s: a value names its row and its seeds;
    its gait too (distance r + 2^s / 1000, upright 2^-s)."""
    space, bodies, names = walker
    fitness = 1000.0 * np.arange(len(bodies))[:, None] + 2.0 ** np.arange(SEEDS)[None]
    gait = (fitness / 1000, np.broadcast_to(2.0 ** -np.arange(SEEDS), fitness.shape))
    diverged = np.zeros(fitness.shape, bool)
    diverged[5, 0] = True
    if nan:
        fitness[3, 2] = np.nan
    keep = [i for i in range(len(bodies)) if i != drop]
    table = tb.Table(space.name, [names[i] for i in keep], tb.stacked([bodies[i] for i in keep]),
                     fitness[keep].astype(np.float32), diverged[keep], {"env_steps_per_result": 7},
                     *(g[keep] for g in gait))
    table.save(path)
    return table


def count_keys(monkeypatch) -> list:
    """Patches `em.evaluate` (as the table builder calls it) to record the keys of each call,
    and to give each result a gait (distance its fitness + 1, upright 0.5: the predefined
    fitness measures none)."""
    evaluated, real = [], em.evaluate

    def counting(space, morphs, keys, cfg):
        evaluated.append(np.asarray(keys))
        res = real(space, morphs, keys, cfg)
        return res.replace(distance=res.fitness + 1, upright=jnp.full_like(res.fitness, 0.5))

    monkeypatch.setattr(em, "evaluate", counting)
    return evaluated


def config(path, k=1, task="distance"):
    return em.FitnessConfig(kind="table", table=str(path), ppo=em.standard_ppo(0, k),
                            task=em.make_task(task))


@pytest.mark.parametrize("name", ["bad_walker", "length_walker"])
def test_signature_tells_bodies_apart_as_canonical_does(name):
    """Over every body reachable from m0, slot by slot (150 Bad Walker arrangements of 90
    bodies; 256 Length Walker bodies): equal signatures exactly when canonical names are."""
    space = em.make_space(name)
    morphs = [m for m, _ in reachable_batched(space)]
    sigs = np.asarray(jax.jit(jax.vmap(tb.signature))(em.stack(morphs)))
    names = [space.canonical(m) for m in morphs]
    pairs = set(zip(map(tuple, sigs), names))
    assert len(pairs) == len(set(names)) == len({tuple(s) for s in sigs})
    assert len(morphs) > len(set(names)) or name == "length_walker"


@pytest.mark.parametrize("k", [1, 3])
def test_draws_come_from_the_bodys_row(walker, tmp_path, k):
    """K = `ppo.controllers` distinct results of the body's own row, their mean and spread,
    and the mean gait of the same K results; every body of every slot arrangement, each with
    its own key."""
    space, _, names = walker
    table = synthetic(walker, tmp_path / "t.npz")
    morphs = [m for m, _ in reachable_batched(space)]
    reps = 4
    batch = em.stack(morphs * reps)
    keys = jax.random.split(jax.random.PRNGKey(k), len(morphs) * reps)
    res = em.evaluate(space, batch, keys, config(tmp_path / "t.npz", k))
    fitness, std, diverged = (np.asarray(x) for x in (res.fitness, res.fitness_std,
                                                     res.diverged))
    rows = np.array([names.index(space.canonical(m)) for m in morphs] * reps)  # by name
    np.testing.assert_array_equal(np.floor(fitness / 1000), rows)
    total = np.round((fitness - 1000 * rows) * k).astype(int)  # sum of 2^s over the draws
    drawn = [[s for s in range(SEEDS) if t >> s & 1] for t in total]
    assert all(len(d) == k for d in drawn), "K distinct results of the row"
    ref = [table.fitness[r, d] for r, d in zip(rows, drawn)]
    np.testing.assert_allclose(fitness, [v.mean() for v in ref], rtol=1e-6)
    np.testing.assert_allclose(std, [v.std() for v in ref], rtol=1e-4, atol=1e-3)
    np.testing.assert_array_equal(diverged, [table.diverged[r, d].any()
                                             for r, d in zip(rows, drawn)])
    for gait in ("distance", "upright"):  # saved, loaded and drawn with the fitness
        np.testing.assert_allclose(getattr(res, gait), [getattr(table, gait)[r, d].mean()
                                                        for r, d in zip(rows, drawn)], rtol=1e-6)
    # over 60 keys every result of m0's row gets drawn, and other keys draw others
    m0 = em.evaluate(space, em.stack([space.initial()] * 60), jax.random.PRNGKey(7),
                     config(tmp_path / "t.npz", k))
    sums = np.round(np.asarray(m0.fitness) * k).astype(int)
    assert np.bitwise_or.reduce(sums) == 2**SEEDS - 1
    again = em.evaluate(space, batch, jax.random.PRNGKey(99), config(tmp_path / "t.npz", k))
    assert (np.asarray(again.fitness) != fitness).any()
    assert res.params is None and res.env_steps == 7 * k


def test_the_gait_round_trips_and_old_tables_have_none(walker, tmp_path):
    """A table's gait survives save and load; a file from before the gait (the packaged
    tables) loads with a NaN gait, and the table fitness's gait of it is NaN."""
    space, bodies, _ = walker
    table = synthetic(walker, tmp_path / "t.npz")
    back = tb.Table.load(tmp_path / "t.npz")
    for gait in (back.distance, back.upright):
        assert gait.dtype == np.float32 and np.isfinite(gait).all()
    np.testing.assert_array_equal(back.distance, table.distance)
    np.testing.assert_array_equal(back.upright, table.upright)
    with np.load(tmp_path / "t.npz") as f:  # as tables were written before the gait
        np.savez_compressed(tmp_path / "old.npz",
                            **{k: f[k] for k in f.files if k not in ("distance", "upright")})
    old = tb.Table.load(tmp_path / "old.npz")
    assert old.distance.shape == old.upright.shape == old.fitness.shape
    assert np.isnan(old.distance).all() and np.isnan(old.upright).all()
    res = em.evaluate(space, em.stack(bodies[:4]), jax.random.PRNGKey(0),
                      config(tmp_path / "old.npz"))
    assert np.isfinite(res.fitness).all()
    assert np.isnan(res.distance).all() and np.isnan(res.upright).all()
    for name in ("bad_walker", "length_walker"):  # the packaged tables, as they are
        with np.load(tb.default_path(name)) as f:
            assert "distance" not in f.files and "upright" not in f.files
        packaged = tb.Table.load(tb.default_path(name))
        assert packaged.distance.shape == packaged.fitness.shape
        assert np.isnan(packaged.distance).all() and np.isnan(packaged.upright).all()


def test_missing_bodies_are_errors_naming_them(walker, tmp_path, monkeypatch):
    space, bodies, names = walker
    synthetic(walker, tmp_path / "t.npz")
    table = tb.Table.load(tmp_path / "t.npz")
    odd = space.initial().replace(attrs=space.initial().attrs.at[2, 0].set(0.33))
    odd_name = space.canonical(odd)
    assert table.row(space, bodies[7]) == 7
    missing = re.escape(f"body {odd_name} is not in the bad_walker table")
    with pytest.raises(ValueError, match=missing):
        table.row(space, odd)  # outside jit
    with pytest.raises(ValueError, match=missing):  # em.evaluate names it before its call
        em.evaluate(space, em.stack([bodies[0], odd]), jax.random.PRNGKey(0),
                    config(tmp_path / "t.npz"))
    # inside jit (an agent's loop, which never meets one): NaN and flagged diverged
    _, evaluate = get_fitness("table").make(space, config(tmp_path / "t.npz"))
    vmapped = jax.jit(jax.vmap(lambda k, m: evaluate(k, m, None)))  # over seeds too
    pairs = jax.tree.map(lambda *x: jnp.stack(x), em.stack([bodies[0]] * 2),
                         em.stack([bodies[1], odd]))
    out = vmapped(jax.random.split(jax.random.PRNGKey(0), 4).reshape(2, 2, -1), pairs)
    inside = np.array([[True, True], [True, False]])
    assert np.isfinite(np.asarray(out.fitness)[inside]).all()
    assert np.isnan(out.fitness[1, 1]) and bool(out.diverged[1, 1])
    assert not np.asarray(out.diverged)[inside].any()
    # a table without a body reachable from m0 is refused when the fitness is made
    synthetic(walker, tmp_path / "gap.npz", drop=len(names) - 1)
    with pytest.raises(ValueError, match=re.escape(f"lacks body {names[-1]}")):
        get_fitness("table").make(space, config(tmp_path / "gap.npz"))
    synthetic(walker, tmp_path / "nan.npz", nan=True)
    with pytest.raises(ValueError, match="incomplete"):
        get_fitness("table").make(space, config(tmp_path / "nan.npz"))
    with pytest.raises(ValueError, match="holds 6 results a body"):
        get_fitness("table").make(space, config(tmp_path / "t.npz", 7))
    with pytest.raises(ValueError, match="is of bad_walker, not length_walker"):
        get_fitness("table").make(em.make_space("length_walker"), config(tmp_path / "t.npz"))
    with pytest.raises(ValueError, match="no table at"):
        config(tmp_path / "none.npz")
    monkeypatch.setattr(tb, "TABLES", tmp_path / "packaged")
    with pytest.raises(ValueError, match="build_tables --space bad_walker"):
        get_fitness("table").make(space, em.FitnessConfig(kind="table"))


def test_one_trace_across_bodies(walker, tmp_path):
    space, bodies, _ = walker
    synthetic(walker, tmp_path / "t.npz")
    _, evaluate = get_fitness("table").make(space, config(tmp_path / "t.npz", 2))
    chex.clear_trace_counter()
    once = jax.jit(chex.assert_max_traces(evaluate, n=1))
    keys = jax.random.split(jax.random.PRNGKey(0), 8)
    for start in (0, 8, 80):
        res = once(keys, em.stack(bodies[start : start + 8]), None)
        assert np.isfinite(np.asarray(res.fitness)).all()


def test_an_agent_runs_on_the_table(walker, tmp_path):
    """The jitted agent loop: every reward is f(child) - f(parent), each a mean of 2 draws from
    the child's own row (the parent's fitness as drawn at its own evaluation). The random
    agent: a table fitness program is compiled afresh every run (its host callback keeps it
    out of the compilation cache), and a learning agent's would cost 20 s more; every agent's
    own loop is test_agent's."""
    from evojax_morph.search.pipeline import RunConfig, build

    space, _, names = walker
    table = synthetic(walker, tmp_path / "t.npz")
    p = build(RunConfig(space="bad_walker", fitness="table", table=str(tmp_path / "t.npz"),
                        agent="random", num_envs=4, horizon=3, controllers=2))
    seeds = jax.vmap(jax.random.PRNGKey)(jnp.arange(2))  # vmapped over seeds, as experiments do
    states = jax.jit(jax.vmap(p.agent.init))(seeds)
    _, metrics = jax.jit(jax.vmap(lambda s: p.agent.chunk(s, 5)))(states)
    bodies = jax.device_get(metrics["bodies"])
    fitness = np.asarray(metrics["fitness"]).reshape(-1)  # (2 seeds x 5 steps x 4 envs,)
    morphs = em.unstack(jax.tree.map(lambda x: x.reshape((-1,) + x.shape[3:]), bodies["morph"]))
    rows = np.array([names.index(space.canonical(m)) for m in morphs])
    np.testing.assert_array_equal(np.floor(fitness / 1000), rows)
    assert np.isin(np.round((fitness - 1000 * rows) * 2),
                   [2**a + 2**b for a in range(SEEDS) for b in range(a)]).all()
    assert table.seeds == SEEDS


def test_builder_resumes_and_refuses_other_settings(walker, tmp_path, monkeypatch, capsys):
    """A build stopped after a batch continues where it stopped and evaluates each (body,
    seed) once; the table of the predefined fitness holds each body's own value and the gait
    `em.evaluate` gave it; it records its task, and serves, and resumes under, no other."""
    space, bodies, names = walker
    out = str(tmp_path / "bw.npz")
    args = ["--space", "bad_walker", "--fitness", "predefined", "--seeds", "2", "--batch", "64",
            "--out", out]
    real, evaluated = em.evaluate, count_keys(monkeypatch)
    build_tables.main(args + ["--max-batches", "1"])
    first = tb.Table.load(out)
    assert first.done.sum() == 64 and not first.done.all()
    build_tables.main(args)
    done = tb.Table.load(out)
    assert len(evaluated) == 3  # 180 results in batches of 64: one, then the other two
    assert "resuming" in capsys.readouterr().out
    np.testing.assert_array_equal(done.fitness[first.done], first.fitness[first.done])
    want = np.asarray(jax.vmap(space.predefined_fitness)(em.stack(bodies)))
    np.testing.assert_allclose(done.fitness, np.stack([want, want], 1))
    assert done.names == names and done.meta["seeds"] == 2 and done.meta["revision"]
    assert done.meta["fitness"]["kind"] == "predefined" and "device" in done.meta
    assert done.meta["task"] == done.task == "distance"
    np.testing.assert_allclose(done.distance, done.fitness + 1)  # count_keys's gait
    np.testing.assert_array_equal(done.upright, 0.5)
    keys = np.concatenate(evaluated)[:180]
    assert len({k.tobytes() for k in keys}) == 180  # no result measured twice
    with pytest.raises(SystemExit, match="other settings"):
        build_tables.main(args[:-2] + ["--seed", "5", "--out", out])
    with pytest.raises(SystemExit, match="other settings") as refused:
        build_tables.main(args + ["--task", "walk"])
    assert "'task': 'distance'" in str(refused.value) and "'task': 'walk'" in str(refused.value)
    build_tables.main(args[:-1] + [str(tmp_path / "walk.npz"), "--task", "walk",
                                   "--max-batches", "1"])
    walk = tb.Table.load(tmp_path / "walk.npz")
    assert walk.task == "walk" and walk.meta["fitness"]["task"]["name"] == "walk"
    # the built table is a table fitness: closed under mutation, m0's row first
    res = real(space, em.stack([space.initial()]), jax.random.PRNGKey(0), config(out))
    np.testing.assert_allclose(res.fitness, want[:1])
    np.testing.assert_allclose(res.distance, want[:1] + 1)
    with pytest.raises(ValueError, match="under the task 'distance', but the fitness asks for "
                                         "'walk'"):
        real(space, em.stack([space.initial()]), jax.random.PRNGKey(0), config(out, task="walk"))


@pytest.mark.slow  # 23 s cold; test_confirm runs `run` on a table in the default set
def test_run_command_with_the_table(walker, tmp_path):
    synthetic(walker, tmp_path / "t.npz")
    out = tmp_path / "run"
    args = ["--space", "bad_walker", "--fitness", "table", "--table", str(tmp_path / "t.npz"),
            "--agent", "qrdqn", "--num-envs", "4", "--steps", "4", "--chunk", "2",
            "--learning-starts", "4", "--out", str(out)]
    assert cli.main(args) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["best_fitness"] >= 1000 and summary["controllers"] == []
    assert json.loads((out / "config.json").read_text())["table"] == str(tmp_path / "t.npz")
    with pytest.raises(SystemExit) as e:
        cli.main(args[:4] + ["--table", str(tmp_path / "none.npz"), "--out", str(tmp_path / "x")])
    assert e.value.code == 2


def test_deep_rows_are_built_and_drawn_from(walker, tmp_path, monkeypatch):
    """`--deep-top 3 --deep-seeds 5` gives the 3 bodies of the highest base means 5 results
    (the keys of the base continued: none measured twice), the others keep 2 (NaN beyond);
    the table fitness draws K among a row's measured results only, all of them in a deep row."""
    space, bodies, names = walker
    out = str(tmp_path / "deep.npz")
    real, evaluated = em.evaluate, count_keys(monkeypatch)
    build_tables.main(["--space", "bad_walker", "--fitness", "predefined", "--seeds", "2",
                       "--batch", "64", "--deep-top", "3", "--deep-seeds", "5", "--out", out])
    table = tb.Table.load(out)
    want = np.asarray(jax.vmap(space.predefined_fitness)(em.stack(bodies)))
    deep = table.meta["deep"]["rows"]
    assert sorted(deep) == sorted(np.argsort(-want, kind="stable")[:3].tolist())
    counts = table.counts()
    assert table.seeds == 5 and table.base == 2 and table.complete
    assert (counts[deep] == 5).all() and (np.delete(counts, deep) == 2).all()
    np.testing.assert_array_equal(np.isnan(table.distance), ~table.done)  # gait where measured
    np.testing.assert_allclose(table.mean(), want, rtol=1e-6)
    keys = np.concatenate(evaluated)
    assert len({k.tobytes() for k in keys}) == 90 * 2 + 3 * 3  # the padding repeats a key
    # draws: a synthetic table with 3 base results and 6 in m0's row
    syn = synthetic(walker, tmp_path / "t.npz")
    syn.fitness[1:, 3:] = np.nan
    syn.meta["seeds"] = 3
    syn.save(tmp_path / "t.npz")
    for row, expect in ((0, 2**SEEDS - 1), (7, 2**3 - 1)):
        res = real(space, em.stack([bodies[row]] * 60), jax.random.PRNGKey(3),
                   config(tmp_path / "t.npz", 3))
        fitness = np.asarray(res.fitness)
        assert np.isfinite(fitness).all()
        sums = np.round((fitness - 1000 * row) * 3).astype(int)
        assert np.bitwise_or.reduce(sums) == expect
    with pytest.raises(ValueError, match="holds 3 results"):
        real(space, em.stack([bodies[0]]), jax.random.PRNGKey(3), config(tmp_path / "t.npz", 4))


def test_freeze_keeps_each_methods_lowest_regret_on_one_table(tmp_path):
    """`compare_table --freeze`: of a folder of tuning runs, each method's setting of the lowest
    confirmed mean regret, with every candidate and the table; runs of two tables refused."""
    from experiments import compare_table

    def run(tag, settings, regrets, space="bad_walker"):
        s = dataclasses.asdict(compare_table.Settings(space=space, seeds=20, tag=tag,
                                                      agent_settings=json.dumps(settings)))
        stats = {"1": {"confirmed": {m: {"mean_regret": [r, r - 1, r + 1], "indistinguishable": 3}
                                     for m, r in regrets.items()}}}
        stats["1"]["confirmed"]["a-b"] = {"diff": 0.0}  # an effect, not a method
        (tmp_path / f"compare_table_{space}_{tag}.json").write_text(json.dumps(
            {"settings": s, "evaluations_per_run": 10_000, "stats": stats}))

    run("tune_a", {"regularized_evolution": {"population": 32}}, {"regularized_evolution": 9.0})
    run("tune_b", {"regularized_evolution": {"population": 64}, "ddqn": {"epsilon_steps": 9}},
        {"regularized_evolution": 4.0, "ddqn": 7.0})
    run("tune_c", {}, {"ddqn": 8.0})
    frozen = compare_table.freeze(tmp_path, tmp_path / "frozen.json")
    assert frozen["settings"] == {"regularized_evolution": {"population": 64},
                                  "ddqn": {"epsilon_steps": 9}}
    assert len(frozen["candidates"]["ddqn"]) == 2 and frozen["tuning_table"].startswith("bad")
    assert json.loads((tmp_path / "frozen.json").read_text()) == frozen
    run("tune_d", {}, {"ddqn": 1.0}, space="length_walker")
    with pytest.raises(SystemExit, match="share a table"):
        compare_table.freeze(tmp_path, tmp_path / "frozen.json")
