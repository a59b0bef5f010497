"""TAME: held-out bodies stay out of training, the fitness terms against numpy, determinism,
batched against one at a time, the Orbax round trip and the CLI."""

import json
import math

import jax
import numpy as np
import pytest

import evojax_morph as em
from evojax_morph import tame
from evojax_morph.run import cli
from evojax_morph.tame import __main__ as tame_cli

TINY = [
    "--episodes",
    "4",
    "--episode-length",
    "20",
    "--population",
    "4",
    "--generations",
    "2",
    "--epochs",
    "2",
]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A classifier trained by the CLI on Bad Walker with every body one mutation from m0 held
    out: the genealogy can then only hold m0 (the root's mutations are no-ops)."""
    out = tmp_path_factory.mktemp("tame") / "classifier"
    assert (
        tame_cli.main(
            [
                "--space",
                "bad_walker",
                "--out",
                str(out),
                "--held-out-depth",
                "1",
                "--held-out",
                "0.99",
                *TINY,
            ]
        )
        == 0
    )
    return out, tame.Pretrained.load(out)


@pytest.mark.slow  # the trained TAME classifier fixture: about 2 minutes cold on 2 cores
def test_held_out_bodies_never_enter_training(trained):
    _, pre = trained
    walker = em.make_space("bad_walker")
    bodies, depths = walker.enumerate_bodies(1)
    one_away = {walker.canonical(b) for b, d in zip(bodies, depths) if d == 1}
    assert set(pre.held_out_bodies) == one_away and len(one_away) > 5
    assert pre.train_bodies == [
        walker.canonical(walker.initial())
    ]  # every other mutation was refused
    assert not set(pre.train_bodies) & set(pre.held_out_bodies)
    for row in pre.history:  # held-out metrics were measured, every generation
        assert -10 < row["held_out_loglik"] < 0 and 0 <= row["held_out_accuracy"] <= 1
    assert (trained[0] / "history.png").stat().st_size > 0


@pytest.fixture(scope="module")
def walker_tame():
    """Bad Walker's TAME at a tiny budget, an untrained classifier and its jitted rollout."""
    walker = em.make_space("bad_walker")
    cfg = tame.TameConfig(episodes=6, episode_length=20, coverage=0.7)
    t = tame.Tame(walker, cfg)
    return (
        walker,
        cfg,
        t,
        tame.init_classifier(walker, cfg, jax.random.PRNGKey(0)),
        jax.jit(t.rollout),
    )


def test_fitness_terms_match_numpy(walker_tame):
    """F = sum_j (log K + mean_e log q(a_j | s_T)) + coverage x 1/2 log det(I + Cov / sigma^2),
    recomputed from the classifier's logits with numpy loops."""
    walker, cfg, t, params, rollout = walker_tame
    m = walker.optimum()
    r = jax.device_get(rollout(jax.random.PRNGKey(3), m))
    assert not r.diverged.any() and r.labelled.tolist() == [
        False,
        False,
        True,
        True,
    ]  # m* has no long foot
    f = tame.fitness_from(cfg, tame.log_likelihood(t.classifier, params, m, r)[0], r)
    k = cfg.num_primitives
    control = 0.0
    for e in range(cfg.episodes):
        logits = np.asarray(t.classifier.apply(params, m, r.states[e]), np.float64)
        for j in np.flatnonzero(r.labelled):
            logq = logits[j] - np.log(np.exp(logits[j]).sum())
            control += (math.log(k) + logq[r.labels[e, j]]) / cfg.episodes
    moved = np.asarray(r.states[:, 0, :2], np.float64)
    coverage = 0.5 * np.log(
        np.linalg.det(np.eye(2) + np.cov(moved.T, bias=True) / cfg.state_noise**2)
    )
    assert coverage > 0.1  # the feet move the trunk
    np.testing.assert_allclose(f, control + cfg.coverage * coverage, rtol=1e-4)


def test_no_motor_no_control_term(walker_tame):
    walker, cfg, t, params, rollout = walker_tame
    trunk = walker.initial()
    for foot in (1, 2, 3):
        trunk = walker.mutate(trunk, foot, 4)  # remove every foot
    r = rollout(jax.random.PRNGKey(0), trunk)
    assert not r.labelled.any()
    loglik, _ = tame.log_likelihood(t.classifier, params, trunk, r)
    control, coverage = tame.fitness_terms(cfg, loglik, r)
    assert float(control) == 0.0
    assert 0 <= float(coverage) < 0.05  # and a trunk without feet stays put


@pytest.mark.slow  # the trained TAME classifier fixture: about 2 minutes cold on 2 cores
def test_fitness_is_deterministic_and_batch_independent(trained):
    out, _ = trained
    walker = em.make_space("bad_walker")
    morphs = em.stack([walker.initial(), walker.optimum(), walker.mutate(walker.initial(), 1, 4)])
    cfg = em.FitnessConfig(kind="tame", classifier=str(out))
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    a, b = em.evaluate(walker, morphs, keys, cfg), em.evaluate(walker, morphs, keys, cfg)
    np.testing.assert_array_equal(a.fitness, b.fitness)
    assert a.env_steps == 4 * 20 and not a.diverged.any()
    other = em.evaluate(walker, morphs, jax.random.split(jax.random.PRNGKey(1), 3), cfg)
    assert not np.allclose(a.fitness, other.fitness)
    for i in range(3):
        pick = jax.tree.map(lambda x, i=i: x[i : i + 1], morphs)
        one = em.evaluate(walker, pick, keys[i : i + 1], cfg)
        np.testing.assert_allclose(one.fitness[0], a.fitness[i], rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="classifier"):
        em.FitnessConfig(kind="tame")
    with pytest.raises(ValueError, match="trained on bad_walker"):
        em.evaluate(
            em.make_space("constructor"),
            em.stack([em.make_space("constructor").initial()]),
            keys[0],
            cfg,
        )


@pytest.mark.slow  # the trained TAME classifier fixture: about 2 minutes cold on 2 cores
def test_cli_refuses_the_tame_fitness_without_its_classifier(trained, tmp_path, capsys):
    out, _ = trained
    with pytest.raises(SystemExit):
        cli.main(["--fitness", "tame", "--out", str(tmp_path / "none")])
    assert "needs --classifier" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(
            [
                "--space",
                "constructor",
                "--fitness",
                "tame",
                "--classifier",
                str(out),
                "--out",
                str(tmp_path / "x"),
            ]
        )
    assert "another space" in capsys.readouterr().err


@pytest.mark.slow  # a whole run (random agent) compiling the TAME fitness's programs: a minute
def test_cli_runs_with_the_tame_fitness(trained, tmp_path):
    out, _ = trained
    assert (
        cli.main(
            [
                "--fitness",
                "tame",
                "--classifier",
                str(out),
                "--agent",
                "random",
                "--steps",
                "2",
                "--num-envs",
                "2",
                "--chunk",
                "2",
                "--confirm",  # its confirm stage would compile the fitness again (test_confirm)
                "0",
                "--out",
                str(tmp_path / "r"),
            ]
        )
        == 0
    )
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert math.isfinite(summary["best_fitness"])


def test_tame_refuses_a_space_whose_limbs_are_not_its_nodes(tmp_path, capsys):
    """The Constructor's template slots are not its bodies' nodes, so TAME cannot label its
    motors: training there exits 2 saying so before anything is written (it raised an
    IndexError), and `Tame` raises ValueError; the other spaces are taken."""
    with pytest.raises(SystemExit) as e:
        tame_cli.main(["--space", "constructor", "--out", str(tmp_path / "c")] + TINY)
    assert e.value.code == 2 and "constructor space's limbs are not its nodes" in (
        capsys.readouterr().err)
    assert not (tmp_path / "c").exists()
    with pytest.raises(ValueError, match="not its nodes"):
        tame.Tame(em.make_space("constructor"))
    assert [s for s in em.list_spaces() if tame.fitness.refused(em.make_space(s))] == [
        "constructor"]
