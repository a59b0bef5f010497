"""A study as one batched program (issue 63), on Bad Walker's table fitness (deterministic, no
training): each method's seeds run as its agent runs them alone, in one fitness call a step."""

import json
import pickle
import re
import shutil
from types import SimpleNamespace

import jax
import numpy as np
import pytest
from conftest import data_files, flip

import evojax_morph as em
from evojax_morph import agents
from evojax_morph.morphology import signature
from evojax_morph.records import bodylog
from evojax_morph.records.checkpoints import DAMAGED, ResumeError
from evojax_morph.search import loop, study
from evojax_morph.search.pipeline import RunConfig
from experiments import common, crawler_study

METHODS = ("ddqn", "a2c", "random", "regularized_evolution", "evolution")
N, SEEDS, STEPS = 4, 2, 4  # a step: 5 methods x 2 seeds x 4 children, one call of 40


def make(names, calls=None):
    """The study of `names` x SEEDS on Bad Walker's table, N evolutions a seed; with `calls`, a
    list, its fitness appends each call's batch size as it is traced."""
    cfg = RunConfig(space="bad_walker", fitness="table", num_envs=N, horizon=3,
                    explore_steps=2, learning_starts=N)
    methods, p = study.methods_from(cfg, names)
    fitness_fn = p.env.fitness_fn

    def counted(*args):
        calls.append(len(args[0]))
        return fitness_fn(*args)

    return methods, study.make_study(methods, SEEDS, fitness_fn if calls is None else counted)


def test_one_fitness_call_a_step_for_every_method_and_seed():
    calls = []
    _, s = make(METHODS, calls)
    states = jax.eval_shape(s.init, jax.random.split(jax.random.PRNGKey(0), SEEDS))
    assert calls == [len(METHODS) * SEEDS * N]  # the start: m0 of every run, one call
    calls.clear()
    _, metrics = jax.eval_shape(lambda st: s.chunk(st, 3), states)
    assert calls == [len(METHODS) * SEEDS * N]  # one call in the scanned step
    assert s.evaluations == len(METHODS) * SEEDS * N and s.methods == METHODS
    for m in METHODS:  # its seeds each, S x N evaluations a step: equal evaluations
        assert states[m].best_fitness.shape == (SEEDS,)
        assert metrics[m]["fitness"].shape == (3, SEEDS, N)
        assert metrics[m]["signature"].shape == (3, SEEDS, N, 2)


def test_the_search_loop_steps_in_chunks_and_stops_at_its_deadline():
    """`search.loop.chunks`, the host's loop of a run and of a study: calls of at most a
    chunk's steps from the steps done, each asked of `program` before its clock starts, its
    metrics on the host; past the deadline no call begins."""
    asked = []

    def program(n):
        asked.append(n)
        return lambda state: (state + n, {"steps": np.arange(n)})

    got = list(loop.chunks(program, 10, 2, 9, 3))
    assert asked == [3, 3, 1]
    assert [(c.step, c.n, c.state) for c in got] == [(5, 3, 13), (8, 3, 16), (9, 1, 17)]
    assert all(len(c.metrics["steps"]) == c.n and c.seconds >= c.dispatch >= 0 for c in got)
    assert list(loop.chunks(program, 0, 0, 9, 3, deadline=0.0)) == [] and len(asked) == 3


def runs_as_alone(names, tmp_path):
    """Seed s of each method in the study against its agent (`from_policy`) run alone from
    keys[s] (its seeds vmapped): the bodies, their fitness, rewards, actions and the best
    bit for bit; a learner's floats within float rounding (XLA fuses the study's one program
    apart from the agent's own, so a Q-network's weights differ in the 7th digit). And the
    same study resumed from its file after 2 steps against one go of 4, bit for bit."""
    methods, s = make(names)
    keys = jax.random.split(jax.random.PRNGKey(3), SEEDS)
    events = []  # an engine's preload (Warp's) is started once and waited for once, at first

    class Loading:
        def result(self):
            events.append("waited")

    whole = study.run_study(s, keys, STEPS, chunk=2, log=lambda _: events.append("chunk"),
                            preload=lambda: events.append("preload") or Loading())
    assert events == ["preload", "waited", "chunk", "chunk"], events
    study.run_study(s, keys, 2, chunk=2, resume=tmp_path / "s")  # a call that stops
    for resume in (tmp_path / "s", newest_damaged(s, keys, tmp_path / "s")):
        said = []
        resumed = study.run_study(s, keys, STEPS, chunk=2, resume=resume, log=said.append)
        for a, b in zip(jax.tree.leaves((whole["states"], whole["metrics"])),
                        jax.tree.leaves((resumed["states"], resumed["metrics"])), strict=True):
            np.testing.assert_array_equal(a, b)
    assert said[0].startswith("checkpoint 2 is damaged, skipped (Damaged: ['states']"), said
    assert "its SHA-256 is not the saved one)" in said[0] and (resume / DAMAGED / "2").is_dir()
    assert whole["evaluations_per_second"] > 0
    for m in methods:
        agent = agents.from_policy(m.env, m.policy)
        state, metrics = jax.jit(jax.vmap(lambda k, a=agent: a.chunk(a.init(k), STEPS)))(keys)
        mine, got = whole["states"][m.name], whole["metrics"][m.name]
        exact = lambda st: (st.evo, st.first, st.step, st.best_fitness, st.best_morph)  # noqa
        for a, b in zip(jax.tree.leaves(exact(state)), jax.tree.leaves(exact(mine))):
            np.testing.assert_array_equal(a, b, err_msg=m.name)
        # A learner's weights part by float rounding that a few Adam steps carry on: at most
        # 5.2e-7 apart here (2 cores, native, AVX2, AVX), 6.5e-7 on CI's machine (a weight of
        # 0.031, relative 2e-5), against weights up to 19: a bound of 1e-5 holds a 15x margin.
        for a, b in zip(jax.tree.leaves(state.learner), jax.tree.leaves(mine.learner)):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5, err_msg=m.name)
        for name, x in metrics.items():
            if name in ("reward", "fitness", "best_fitness", "action"):
                np.testing.assert_array_equal(np.swapaxes(x, 0, 1), got[name], err_msg=m.name)
            elif name != "bodies":
                np.testing.assert_allclose(np.swapaxes(x, 0, 1), got[name], rtol=1e-5,
                                           atol=1e-7, err_msg=m.name)


def newest_damaged(s, keys, folder):
    """A copy of the study's saves in `folder` (steps 0 and 2: a run's checkpoints, Orbax with
    the SHA-256 of every array) with the newest's digest of one array changed (as its bytes
    read as other values would make it): a resume of it goes on from step 0, says which was
    skipped and why and keeps it aside. With step 0's arrays damaged too (bytes inverted in
    its data files: they do not read) a resume raises `ResumeError` with both reasons before
    anything runs, the saves left as they were."""
    assert sorted(int(d.name) for d in (folder / "checkpoints").iterdir()) == [0, 2]
    newest, both = folder.with_name("newest_damaged"), folder.with_name("both_damaged")
    shutil.copytree(folder, newest)
    digest = newest / "checkpoints" / "2" / "digest" / "metadata"
    saved = json.loads(digest.read_text())
    array = next(k for k in saved if k.startswith("['states']"))
    digest.write_text(json.dumps({**saved, array: "0" * 64}))
    shutil.copytree(newest, both)
    for f in data_files(both / "checkpoints" / "0"):
        if "state" in f.parts:  # the arrays' (not the record's or the digests' JSON)
            flip(f)
    before = {f: f.read_bytes() for f in sorted(both.rglob("*")) if f.is_file()}
    with pytest.raises(ResumeError, match=re.escape(f"step 2: Damaged: {array}: its SHA-256 is "
                                                    "not the saved one; step 0: ")):
        study.run_study(s, keys, STEPS, chunk=2, resume=both)
    assert before == {f: f.read_bytes() for f in sorted(both.rglob("*")) if f.is_file()}
    return newest


def test_the_baselines_run_as_alone_and_resume_as_one_go(tmp_path):
    runs_as_alone(("random", "evolution"), tmp_path)


@pytest.mark.slow  # 166 s cold on 2 shared cores: the learners' programs, alone and together
def test_every_method_runs_as_alone_and_resumes_as_one_go(tmp_path):
    runs_as_alone(METHODS, tmp_path)


def test_an_experiments_agent_runs_as_a_study_of_one_method(tmp_path):
    """`experiments.common.run_agent`: seed s from split(PRNGKey(0), S)[s], run as its agent
    runs alone (its seeds vmapped: run_agent's own loop before issue 64), bit for bit; stopped
    at its deadline, called again, it resumes; per-step arrays are (steps, seeds, ...)."""
    setup = common.Setup(space="bad_walker", fitness="table", num_envs=N, steps=6, chunk=4)
    resume = tmp_path / "run.state"
    assert common.run_agent("evolution", setup, SEEDS, resume, deadline=0) is None
    res = common.run_agent("evolution", setup, SEEDS, resume)
    agent = res["pipeline"].agent
    keys = jax.random.split(jax.random.PRNGKey(0), SEEDS)
    state, metrics = jax.jit(jax.vmap(lambda k: agent.chunk(agent.init(k), 6)))(keys)
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(res["states"]), strict=True):
        np.testing.assert_array_equal(a, b)
    for name, x in metrics.items():
        if name != "bodies":
            np.testing.assert_array_equal(np.swapaxes(x, 0, 1), res["metrics"][name])
    assert res["metrics"]["reward"].shape == (6, SEEDS, N)
    assert res["step_seconds"].shape == (6,) and res["seconds"] >= res["init_seconds"] > 0
    np.testing.assert_array_equal(res["best_fitness"], state.best_fitness)
    assert len(res["best_bodies"]) == SEEDS


def test_a_run_returns_its_body_of_the_highest_mean_not_its_best_draw():
    """`study.best_mean_bodies` on hand-made draws: seed 0's best draw (A, 10) is luck, A's mean
    5; B and C both mean 7, B drawn 3 times, C once and first: B. Seed 1: E and F both mean 3
    in 2 draws, E seen first; D's NaN puts it last despite its 100. Steps after `upto_steps`
    are not counted; the start (`first`) is, before step 0, its bodies told apart by their
    signature."""
    a, b, c, d, e, f = range(6)
    bodies = np.array([[[a, c], [d, e]], [[b, a], [f, e]], [[b, b], [f, d]]])  # (T, S, N)
    fitness = np.array([[[10, 7], [np.nan, 1]], [[7, 0], [3, 5]], [[7, 7], [3, 100]]])
    metrics = {"signature": np.stack([bodies, bodies], -1).astype(np.uint32),
               "fitness": fitness.astype(np.float32), "morph": bodies}
    found = study.best_mean_bodies(metrics, 3)
    assert [(r["morph"], r["mean"], r["draws"]) for r in found] == [(b, 7, 3), (e, 3, 2)]
    np.testing.assert_array_equal(found[0]["signature"], [b, b])
    assert bodies[:, 0].flat[np.nanargmax(fitness[:, 0])] == a  # the best single draw's
    assert [r["morph"] for r in study.best_mean_bodies(metrics, 2)] == [c, e]  # 7 once, first
    assert [r["morph"] for r in study.best_mean_bodies(metrics, 1)] == [a, e]

    m0 = em.make_space("bad_walker").initial()
    x = m0.replace(attrs=m0.attrs + 0.5)
    first = SimpleNamespace(morph=em.stack([em.stack([m0, m0])]), fitness=np.array([[4.0, 4]]))
    children = em.stack([em.stack([em.stack([x, m0])])])  # (T=1, S=1, N=2)
    metrics = {"signature": np.asarray(jax.vmap(jax.vmap(jax.vmap(signature)))(children)),
               "fitness": np.array([[[5.0, 1]]]), "morph": children}
    (start,) = study.best_mean_bodies(metrics, 0, first)
    (end,) = study.best_mean_bodies(metrics, 1, first)
    assert (start["draws"], start["mean"], end["draws"], end["mean"]) == (2, 4, 1, 5)
    np.testing.assert_array_equal(start["morph"].attrs, m0.attrs)
    np.testing.assert_array_equal(end["morph"].attrs, x.attrs)
    (m0_mean,) = study.best_mean_bodies({**metrics, "fitness": np.array([[[2.0, 4]]])}, 1, first)
    assert (m0_mean["draws"], m0_mean["mean"]) == (3, 4)  # m0's 3 draws, its child's among them


def test_a_study_and_the_body_log_rank_alike(tmp_path):
    """One rule ranks a run's bodies (`bodylog.ranked`): two bodies tied on their mean, their
    draws and the step they were first seen go to the first by canonical name, in the body log
    and in a study alike, whichever child made it."""
    space = em.make_space("bad_walker")
    m0 = space.initial()
    x, y = (m0.replace(attrs=m0.attrs + d) for d in (0.25, 0.5))
    first, later = sorted([x, y], key=space.canonical)
    for pair in ([first, later], [later, first]):
        log = bodylog.BodyLog(tmp_path / f"{len(list(tmp_path.iterdir()))}.sqlite", space)
        log.add(0, em.stack(pair), np.ones(2), np.zeros(2), np.zeros(2, bool))
        log.commit()
        log.close()
        (logged,) = em.best_bodies(log.path, 1)
        children = em.stack([em.stack([em.stack(pair)])])  # (T=1, S=1, N=2)
        metrics = {"signature": np.asarray(jax.vmap(jax.vmap(jax.vmap(signature)))(children)),
                   "fitness": np.ones((1, 1, 2), np.float32), "morph": children}
        (found,) = study.best_mean_bodies(metrics, 1)
        assert logged["body"] == space.canonical(found["morph"]) == space.canonical(first)
    asked = []
    ranked = bodylog.ranked([1.0, 2.0, np.nan], [1, 1, 1], [0, 0, 0], asked.append, 3)
    assert ranked == [1, 0, 2]
    assert asked == []  # a name is asked only to break a tie


def test_every_run_and_body_confirms_with_keys_of_its_own():
    """No two runs (method, seed) of the study, nor two returned bodies of a run, share a
    confirming key; a body's controllers each take their own."""
    keys = [crawler_study.confirm_keys(m, seed, body, 16) for m in METHODS
            for seed in range(10) for body in range(3)]
    assert len({tuple(np.asarray(k)) for ks in keys for k in ks}) == len(METHODS) * 10 * 3 * 16


def test_a_returned_body_walks_as_tasks_defines_it():
    entry = lambda d, u: {"distance": d, "upright_whole": u}  # noqa: E731
    assert [crawler_study.gait(entry(*e)) for e in ((2.0, 0.9), (1.9, 1.0), (3.0, 0.8),
                                                    (np.nan, 1.0))] == \
        ["walks", "moves", "moves", None]


def test_the_picks_are_ranked_against_their_confirmations_off_the_start():
    """`crawler_study.picks` on hand-made runs: the four bodies off m0 rank backwards (in the
    run 200 < 300 < 400 < 500, confirmed 180 > 150 > 120 > 90): Spearman -1; the run that
    stays at m0 is left out, whatever its numbers; with 2 runs off m0, None."""
    def run(*returned):  # (mean in the run, its draws, body, confirmed mean) a seed
        mean, draws, body, confirmed = zip(*returned)
        return {"returned_mean": mean, "returned_draws": draws,
                "returned": [{"body": b, "mean": c} for b, c in zip(body, confirmed)]}

    runs = {"a": run((200, 1, "b1", 180), (300, 2, "b2", 150)),
            "b": run((400, 1, "b3", 120), (500, 1, "b4", 90)),
            "c": run((100, 40, "m0", 1000), (600, 30, "m0", 0))}
    got = crawler_study.picks(runs, "m0")
    assert (got["runs"], got["one_draw"], got["in_run_mean"], got["confirmed"]) == \
        (4, 3, [200, 500], [90, 180])
    assert got["spearman"] == pytest.approx(-1)
    assert crawler_study.picks({"a": runs["a"], "c": runs["c"]}, "m0") is None


@pytest.mark.slow  # 65 s cold: the five agents on Bad Walker's table, confirmed
def test_the_toy_study_leaves_every_method_its_seeds_at_equal_evaluations(tmp_path):
    """`python -m experiments.crawler_study --toy`: every method's seeds, each with its returned
    body confirmed, equal evaluations, the curve and the distinct bodies, every draw of its
    steps in the part's results; the leases of held.jsonl summed; the figure."""
    (tmp_path / "crawler_study").mkdir()
    (tmp_path / "crawler_study" / "held.jsonl").write_text(
        '{"held_seconds": 100.5}\n{"held_seconds": 20.25}\n')
    crawler_study.main(["--toy", "--out", str(tmp_path)])
    data = json.loads((tmp_path / "study_bad_walker_distance.json").read_text())
    assert set(data["runs"]) == set(METHODS) and data["seed_indices"] == [0, 1]
    assert [p["evaluations_per_call"] for p in data["parts"]] == [5 * 2 * 4]  # one part
    for r in data["runs"].values():
        assert len(r["returned"]) == len(r["distinct_bodies"]) == data["seeds"] == 2
        assert r["curve"][-1]["evaluations"] == data["evaluations_per_run"] == 4 * 6
        assert all(len(p["confirmed"]) == 2 for p in r["curve"])
        assert {"distance", "upright", "upright_whole"} <= set(r["returned"][0])
        assert r["returned_gait"] == [None, None]  # Bad Walker's distance table keeps no gait
        assert len(r["returned_mean"]) == len(r["returned_draws"]) == 2
        assert all(n >= 1 for n in r["returned_draws"])
    assert all("p_holm" in d for d in data["effects"]["differences"].values())
    m0 = em.make_space("bad_walker")
    off = sum(e["body"] != m0.canonical(m0.initial()) for r in data["runs"].values()
              for e in r["returned"])  # the returned bodies the picks rank
    assert off >= 3 and data["picks"]["runs"] == off and -1 <= data["picks"]["spearman"] <= 1
    assert data["held_seconds"] == 120.8 and len(data["leases"]) == 2
    part = pickle.loads((tmp_path / "crawler_study/seeds_0-1/results.pkl").read_bytes())
    assert all(r["draws"].shape == (6, 4) for r in part["runs"])  # steps x N
    assert (tmp_path / "study_bad_walker_distance.png").stat().st_size > 0
