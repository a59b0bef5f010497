"""The confirm stage: `em.confirm`'s fresh evaluations and interval, the body log ranked by mean,
and `run` on a table with a planted lucky body (cheap: the table fitness, the random agent)."""

import json
import shutil
import sqlite3

import jax
import numpy as np
import pytest
import scipy.stats
from conftest import truncate

import evojax_morph as em
from evojax_morph.fitnesses import table as tb
from evojax_morph.records import bodylog
from evojax_morph.records.checkpoints import seal
from evojax_morph.run import cli
from evojax_morph.search import confirm as confirming

S = 8  # results a body in the tables here
STEADY, LUCKY, UNLUCKY = 350.0, 400.0, -1000.0


@pytest.fixture(scope="module")
def walker():
    space = em.make_space("bad_walker")
    bodies, _ = space.enumerate_bodies()
    return space, bodies, [space.canonical(m) for m in bodies]


def save_table(walker, path, fitness) -> None:
    space, bodies, names = walker
    tb.Table(space.name, names, tb.stacked(bodies), np.asarray(fitness, np.float32),
             np.zeros(np.shape(fitness), bool), {}).save(path)


@pytest.fixture(scope="module")
def planted(walker, tmp_path_factory):
    """A 4-step run on a table where m0 scores 350 every time and every other body 400 in 2 of
    8 draws, else -1000 (mean -650): a lucky draw is the run's highest, m0 the best body (8
    fresh draws of another body beat 350 only if all 8 are 400)."""
    space, bodies, _ = walker
    fitness = np.full((len(bodies), S), UNLUCKY)
    fitness[:, :2] = LUCKY
    fitness[0] = STEADY  # enumerate_bodies starts at m0
    path = tmp_path_factory.mktemp("table") / "planted.npz"
    save_table(walker, path, fitness)
    out = tmp_path_factory.mktemp("planted") / "run"
    args = ["--space", "bad_walker", "--fitness", "table", "--table", str(path), "--agent",
            "random", "--num-envs", "4", "--steps", "4", "--chunk", "2", "--seed", "1",
            "--confirm", "8", "--confirm-controllers", "8", "--out", str(out)]
    assert cli.main(args) == 0
    return out, args


def test_a_lucky_draw_is_not_the_best_body(planted, walker):
    out, _ = planted
    space, _, names = walker
    summary = json.loads((out / "summary.json").read_text())
    draw, confirmed = summary["best_single_draw"], summary["confirmed"]
    assert draw["fitness"] == LUCKY and draw["body"] != names[0]  # the run was fooled by a draw
    assert names[0] in [c["body"] for c in confirmed]  # m0 was a candidate
    assert summary["best_body"] == confirmed[0]["body"] == names[0]
    assert summary["best_fitness"] == confirmed[0]["mean"] == STEADY
    assert confirmed[0]["ci95"] == [STEADY, STEADY]  # the same value 8 times
    assert space.canonical(em.Morphology.from_dict(summary["best_morphology"])) == names[0]
    assert (out / "best.xml").read_text() == space.to_mjcf(space.initial())
    for c in confirmed:
        assert c["controllers"] == len(c["values"]) == 8
        assert set(c["values"]) <= ({STEADY} if c["body"] == names[0] else {LUCKY, UNLUCKY})
    means = [c["mean"] for c in confirmed]
    assert means == sorted(means, reverse=True)
    assert (out / "confirmed.png").stat().st_size > 0
    assert summary["best_bodies"] == em.best_bodies(out / "bodies.sqlite", 10)


def test_resume_of_a_finished_run_does_not_confirm_again(planted, tmp_path, monkeypatch,
                                                          capsys):
    out, args = planted
    again = tmp_path / "run"
    shutil.copytree(out, again)

    def no_call(*_, **__):
        raise AssertionError("confirmed again")

    monkeypatch.setattr(confirming, "confirm", no_call)
    assert cli.main(["--out", str(again), "--resume", "--steps", "4"]) == 0
    for name in ("summary.json", "confirmed.json"):
        assert (again / name).read_text() == (out / name).read_text()

    # Another run's confirmed.json (sealed, but of another body log) is not kept: confirmed again.
    record = json.loads((again / "confirmed.json").read_text())
    record["log"]["sha256"] = "0" * 64
    (again / "confirmed.json").write_text(json.dumps(seal(record)))
    with pytest.raises(AssertionError, match="confirmed again"):
        cli.main(["--out", str(again), "--resume", "--steps", "4"])
    (again / "confirmed.json").write_text((out / "confirmed.json").read_text())

    # Read back only as it was written: a value changed, or the file cut short, is an error.
    record = json.loads((again / "confirmed.json").read_text())
    record["confirmed"][0]["mean"] += 1.0
    (again / "confirmed.json").write_text(json.dumps(record))
    with pytest.raises(SystemExit) as e:
        cli.main(["--out", str(again), "--resume", "--steps", "4"])
    assert e.value.code == 2
    assert "confirmed.json is damaged: its SHA-256 is not the saved one" in capsys.readouterr().err
    truncate(again / "confirmed.json")
    with pytest.raises(SystemExit) as e:
        cli.main(["--out", str(again), "--resume", "--steps", "4"])
    assert e.value.code == 2
    assert "confirmed.json does not read (JSONDecodeError: " in capsys.readouterr().err


def test_the_greedy_trajectory_joins_the_confirm_call(walker, tmp_path, monkeypatch):
    """Where the confirm stage confirms, the greedy trajectory's bodies join its one fitness
    call (issue 61): one call of (confirm + horizon + 1) x C evaluations, the greedy bodies
    last, none apart; each greedy body's fitness is the mean of its C values there; the
    confirmed bodies (confirmed.json, the best body) are the body log's alone; a --resume of
    the finished run keeps the trajectory's results and evaluates nothing."""
    from evojax_morph.search import confirm as confirm_module
    from evojax_morph.search import pipeline

    space = walker[0]
    calls, evaluate = [], confirm_module.evaluate

    def counted(*args, **kwargs):
        res = evaluate(*args, **kwargs)
        calls.append((jax.device_get(args[1]), np.asarray(res.fitness)))
        return res

    def apart(p):
        return lambda *_: pytest.fail("the greedy bodies evaluated in a call of their own")

    monkeypatch.setattr(confirm_module, "evaluate", counted)
    monkeypatch.setattr(pipeline, "make_greedy_evaluation", apart)
    n, h, c = 2, 2, 3
    out = tmp_path / "run"
    assert cli.main(["--space", "bad_walker", "--fitness", "table", "--num-envs", "4",
                     "--steps", "4", "--chunk", "2", "--explore-steps", "4",
                     "--learning-starts", "8", "--horizon", str(h), "--confirm", str(n),
                     "--confirm-controllers", str(c), "--out", str(out)]) == 0
    assert len(calls) == 1
    morphs, values = calls[0]
    assert values.shape == ((n + h + 1) * c,)
    called = [space.canonical(jax.tree.map(lambda x, i=i: x[i * c], morphs))
              for i in range(n + h + 1)]
    per_body = values.reshape(n + h + 1, c).astype(np.float64)

    summary = json.loads((out / "summary.json").read_text())
    greedy = summary["greedy_trajectory"]
    assert [space.canonical(em.Morphology.from_dict(g["morphology"])) for g in greedy] == \
        called[n:]
    assert [g["fitness"] for g in greedy] == per_body[n:].mean(1).tolist()
    assert [g["controllers"] for g in greedy] == [c] * (h + 1)

    logged = [b["body"] for b in em.best_bodies(out / "bodies.sqlite", n)]
    record = json.loads((out / "confirmed.json").read_text())
    assert sorted(e["body"] for e in record["confirmed"]) == sorted(logged) == sorted(called[:n])
    for e in record["confirmed"]:
        assert e["values"] == per_body[called[:n].index(e["body"])].tolist()
    means = [e["mean"] for e in record["confirmed"]]
    assert means == sorted(means, reverse=True)
    assert summary["best_body"] == record["confirmed"][0]["body"]
    assert [g["body"] for g in record["greedy"]] == called[n:]

    # A --resume of the finished run evaluates nothing: the trajectory is the first finish's.
    again = tmp_path / "again"
    shutil.copytree(out, again)
    calls.clear()
    assert cli.main(["--out", str(again), "--resume", "--steps", "4"]) == 0
    assert calls == []
    for name in ("summary.json", "confirmed.json"):
        assert (again / name).read_text() == (out / name).read_text()


def test_confirm_interval_and_values(walker, tmp_path):
    """Every value a draw of the body's own row (row r's values are 1000 r + s), the mean and
    the Student-t interval of those values, best first; the values are em.evaluate's of the
    bodies repeated C times with one controller each, with the same key."""
    space, bodies, _ = walker
    fitness = 1000.0 * np.arange(len(bodies))[:, None] + np.arange(S)[None] ** 2
    save_table(walker, tmp_path / "t.npz", fitness)
    cfg = em.FitnessConfig(kind="table", table=str(tmp_path / "t.npz"),
                           ppo=em.standard_ppo(0, 3))  # the run's K does not matter
    rows, c = [2, 7, 5], 5
    key = jax.random.PRNGKey(4)
    found = em.confirm(space, em.stack([bodies[r] for r in rows]), key, cfg, c)
    assert [f.body for f in found] == [space.canonical(bodies[r]) for r in (7, 5, 2)]
    for f, r in zip(found, (7, 5, 2)):
        assert f.values.shape == (c,) and f.params is None and not f.diverged.any()
        assert set(f.values - 1000 * r) <= set(np.arange(S) ** 2)
        values = f.values.astype(np.float64)
        assert f.mean == values.mean()
        half = scipy.stats.t.ppf(0.975, c - 1) * values.std(ddof=1) / np.sqrt(c)
        np.testing.assert_allclose(f.ci95, [f.mean - half, f.mean + half], rtol=1e-9)
        assert f.ci95[0] <= f.mean <= f.ci95[1]
    one = em.FitnessConfig(kind="table", table=str(tmp_path / "t.npz"), ppo=em.standard_ppo(0))
    direct = em.evaluate(space, em.stack([bodies[r] for r in rows for _ in range(c)]), key, one)
    by_row = dict(zip(rows, np.asarray(direct.fitness).reshape(len(rows), c)))
    for f, r in zip(found, (7, 5, 2)):
        np.testing.assert_array_equal(f.values, by_row[r])
    with pytest.raises(ValueError, match="at least 2"):
        em.confirm(space, em.stack(bodies[:2]), key, cfg, 1)
    # unranked: in the order of the bodies, a body given twice measured twice, apart
    again = em.confirm(space, em.stack([bodies[r] for r in rows + [7]]), key, cfg, c,
                       ranked=False)
    assert [f.body for f in again] == [space.canonical(bodies[r]) for r in rows + [7]]
    np.testing.assert_array_equal(again[1].values, by_row[7])
    assert not np.array_equal(again[1].values, again[3].values)


def test_body_log_ranks_by_mean(tmp_path):
    """Mean first, then more evaluations, then the step first seen; the best draw apart."""
    path = tmp_path / "bodies.sqlite"
    space = em.make_space("bad_walker")
    bodylog.BodyLog(path, space).close()
    rows = [(0, 0, "lucky", 90.0), (1, 0, "lucky", 0.0), (1, 1, "single", 40.0),
            (2, 0, "steady", 40.0), (2, 1, "steady", 40.0), (3, 0, "late", 40.0)]
    db = sqlite3.connect(path)
    db.executemany("INSERT INTO bodies VALUES (?, ?, ?, ?, 0, 0, NULL, NULL, NULL)", rows)
    db.commit()
    db.close()
    best = em.best_bodies(path)
    assert [b["body"] for b in best] == ["lucky", "steady", "single", "late"]
    assert [b["evaluations"] for b in best] == [2, 2, 1, 1]
    assert best[0]["mean_fitness"] == 45.0 and best[0]["best_fitness"] == 90.0
    assert bodylog.best_draw(path) == {"body": "lucky", "fitness": 90.0, "step": 0}


def test_body_log_keeps_the_gait(tmp_path):
    """Each evaluation's distance and upright, NULL where the fitness measured none (NaN), and
    each body's means of them; a log begun before the gait was kept gets the two columns."""
    path = tmp_path / "bodies.sqlite"
    db = sqlite3.connect(path)  # the schema before issue 44
    db.execute("CREATE TABLE bodies (step INTEGER NOT NULL, evolution INTEGER NOT NULL, "
               "body TEXT NOT NULL, fitness REAL NOT NULL, fitness_std REAL NOT NULL, "
               "diverged INTEGER NOT NULL, parent TEXT)")
    db.execute("INSERT INTO bodies VALUES (0, 0, 'old', 1.0, 0, 0, NULL)")
    db.commit()
    db.close()
    space = em.make_space("bad_walker")
    walker, m0 = space.optimum(), space.initial()
    log = bodylog.BodyLog(path, space)
    for step, distance, upright in ((1, [2.0, np.nan], [1.0, np.nan]), (2, [4.0, 1.0], [0.5, 1.0])):
        log.add(step, em.stack([walker, m0]), np.array([200.0, 100.0]), np.zeros(2),
                np.zeros(2, bool), distance=np.array(distance), upright=np.array(upright))
    log.commit()
    log.close()
    best = {b["body"]: b for b in em.best_bodies(path)}
    assert best[space.canonical(walker)]["mean_distance"] == 3.0
    assert best[space.canonical(walker)]["mean_upright"] == 0.75
    assert best[space.canonical(m0)]["mean_distance"] == 1.0  # the NULL left out of the mean
    assert best["old"]["mean_distance"] is None and best["old"]["mean_upright"] is None
