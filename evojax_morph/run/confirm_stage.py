"""A run's confirm stage: the bodies of the highest mean in its body log confirmed (`confirm`),
the greedy trajectory's bodies evaluated (in the same fitness call where it confirms now), and
the body the run reports as its best chosen (`reported_best`).

It writes and reads its own files, confirmed.json and the controllers of the best body and of
the greedy trajectory (`save_controllers`), and hands the report stage a `Best`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np

from evojax_morph.fitnesses import FitnessConfig, get_fitness
from evojax_morph.morphology import Morphology
from evojax_morph.records import bodylog, checkpoints, saved_controllers
from evojax_morph.run.compile_ahead import Job
from evojax_morph.search.confirm import Confirmed, confirm, lower_confirm, rank
from evojax_morph.search.pipeline import Greedy, Pipeline, RunConfig
from evojax_morph.sharding import to_host

CONFIRM_SALT = 0x636F6E66  # the confirm stage's key: fold_in(PRNGKey(seed), CONFIRM_SALT)


class Best(NamedTuple):
    """What the confirm stage hands down: the body the run reports as its best, and the rest."""

    morph: Morphology
    fitness: float
    record: dict  # confirmed.json's
    top: Confirmed | None  # the confirmed best, when evaluated now
    saved: list[str]  # the controllers saved
    greedy: Greedy | None  # the greedy trajectory, evaluated; None for the baselines


def confirm_skipped(cfg: RunConfig) -> str | None:
    """Why the confirm stage evaluates nothing (confirmed.json's note), None where it does: the
    one place this is decided."""
    if cfg.confirm == 0:
        return "not run (--confirm 0): the best body is the highest single draw, a noisy maximum"
    if get_fitness(cfg.fitness).deterministic:
        return (f"not run: the {cfg.fitness} fitness is deterministic, so an evaluation again "
                "gives the same values; the best body is the highest single draw")
    return None


def best_controllers(cfg: RunConfig, p: Pipeline) -> FitnessConfig:
    """The fitness config of the controllers `reported_best` leaves (best.gif replays them):
    the confirm stage's C fresh ones, else the run's."""
    return p.fitness if confirm_skipped(cfg) else p.fitness.with_controllers(
        cfg.confirm_controllers)


def kept_record(out: Path, cfg: RunConfig, step: int, log: dict | None) -> dict | None:
    """confirmed.json's record where the run was confirmed at `step` with these settings from
    the body log whose proof the restored checkpoint holds (`log`; None: none restored), so a
    --resume of a finished run does not do it again; else None (another run's file, or one of
    a log since gone on). Raises `Damaged` where the file does not read."""
    done = out / "confirmed.json"
    if not done.exists():
        return None
    before = checkpoints.read_sealed(done)
    now = {"env_steps": step, "bodies": cfg.confirm, "controllers": cfg.confirm_controllers,
           "log": log}
    return before if log is not None and all(before.get(k) == v for k, v in now.items()) else None


def confirms_now(run, step: int) -> bool:
    """Whether the confirm stage of `run` (`driver.Run`) ending at `step` evaluates bodies:
    not skipped (`confirm_skipped`), not kept (`kept_record`). Then the greedy trajectory's
    bodies join its fitness call; else they have one of their own
    (`pipeline.make_greedy_evaluation`)."""
    return not confirm_skipped(run.cfg) and kept_record(run.out, run.cfg, step,
                                                        run.resumed_log) is None


def greedy_apart(run, step: int) -> bool:
    """Whether the greedy trajectory's bodies need a fitness call of their own at `step`: where
    the confirm stage evaluates nothing now (`confirms_now`) and confirmed.json keeps no
    results of theirs (`kept_greedy`: a finished run resumed keeps them)."""
    if confirm_skipped(run.cfg):
        return True
    kept = kept_record(run.out, run.cfg, step, run.resumed_log)  # None: confirms now, with it
    return kept is not None and not kept.get("greedy")


def kept_greedy(record: dict, greedy: Greedy, space) -> Greedy | None:
    """`greedy` with the results confirmed.json's `record` kept for its bodies (a --resume of
    a finished run, which then evaluates them again no more than the rest: its summary and
    trajectory stay the first finish's, and controllers/stepT as saved then), or None where the
    record holds none for these bodies."""
    entries = record.get("greedy") or []
    if [e["body"] for e in entries] != [space.canonical(m) for m in greedy.morphs]:
        return None
    return greedy._replace(fitness=[e["mean"] for e in entries], params=None,
                           controllers=record["controllers"], confirmed=True)


def greedy_bodies(p: Pipeline) -> int:
    """The bodies of the greedy trajectory, m0 first; 0 for a baseline (no policy to roll out)."""
    return 0 if p.agent.scores is None else p.greedy_env.horizon + 1


def confirm_jobs(run, step: int) -> list[Job]:
    """The confirm stage's one fitness call at `step`, where it makes one, for compiling ahead:
    cfg.confirm bodies and the greedy trajectory's, C times each."""
    cfg, p = run.cfg, run.p
    bodies = cfg.confirm + greedy_bodies(p)
    return [Job("confirm", lambda: lower_confirm(
        p.space, bodies, p.fitness, cfg.confirm_controllers))] if confirms_now(run, step) else []


def confirm_stage(run, evolved, ahead, clock) -> Best:
    """The confirm stage, from the earlier stages' results `run` (`driver.Run`) and `evolved`
    (`driver.Evolved`): the bodies of the log confirmed with the walked greedy trajectory's in
    one fitness call (`confirm_record`), or, where it confirms nothing now, the greedy
    trajectory evaluated alone (`pipeline.make_greedy_evaluation`); the run's best chosen
    (`reported_best`), its and the greedy trajectory's controllers saved, and confirmed.json
    written (if confirmed now, lead process); every process calls it."""
    p, cfg, state, greedy = run.p, run.cfg, evolved.state, evolved.greedy
    draw = to_host((state.best_morph, state.best_fitness, state.best_params))
    ahead.wait("confirm")
    record, top, joined = confirm_record(run.out, p, cfg, evolved.step, run.log,
                                         None if greedy is None else greedy.morphs,
                                         run.resumed_log)
    if joined is not None:
        greedy = greedy_confirmed(greedy, joined)
    elif greedy is not None:
        greedy = (kept_greedy(record, greedy, p.space)
                  or run.greedy_evaluation(greedy, run.key_greedy))
    clock.phase("confirm")
    ahead.close()  # best.gif's replay and GL
    best, best_fitness, best_params, best_cfg = reported_best(
        run.out, p, record, top, (draw[0], float(draw[1]), draw[2]))
    saved = save_controllers(run.out, p, cfg.seed, best, best_fitness, best_params,
                             greedy, best_cfg)
    clock.phase("controllers")
    if top is not None and run.lead:  # written last: the stage is done, a --resume keeps it
        record["best_morphology"] = best.to_dict()
        record["log"] = evolved.log  # whose bodies: a --resume keeps it for this log alone
        checkpoints.write_atomic(run.out / "confirmed.json",
                                 json.dumps(checkpoints.seal(record), indent=1))
    return Best(best, best_fitness, record, top, saved, greedy)


def confirm_record(out: Path, p: Pipeline, cfg: RunConfig, step: int, log=print,
                   greedy: list | None = None, resumed_log: dict | None = None):
    """The bodies of a run's log confirmed, the greedy trajectory's `greedy` in the same call;
    every process calls it, after the body log is written.

    The `cfg.confirm` distinct bodies of the highest mean in the body log (`bodylog.
    best_bodies`: ties to the body evaluated more often, then to the one seen first), then the
    bodies `greedy`, are each evaluated `cfg.confirm_controllers` times from scratch, in one
    fitness call (`confirm`): fresh controllers, no inheritance, keys from
    `fold_in(PRNGKey(seed), CONFIRM_SALT)`, which no other part of the run uses. The greedy
    bodies only ride along (one call's latency instead of two, issue 61): they enter neither
    the record nor the choice of the best. Skipped, with a note saying why (`confirm_skipped`);
    not done again when confirmed.json says it was done at this step with these settings, from
    the body log the restored checkpoint proves (`resumed_log`; `kept_record`: a --resume of a
    finished run).

    Returns:
      (record, top, joined): record is what confirmed.json keeps (env_steps, bodies,
      controllers, "confirmed": summary entries best first, "confirm_note"); top is the best
      `Confirmed` when it was evaluated now, else None; joined the `Confirmed` of each body of
      `greedy`, in its order, when evaluated now, else None.
    """
    n, c = cfg.confirm, cfg.confirm_controllers
    record = {"env_steps": step, "bodies": n, "controllers": c, "confirmed": []}
    before = kept_record(out, cfg, step, resumed_log)
    if before is not None:
        log("confirm: done when the run finished, kept (confirmed.json)")
        return before, None, None
    if (out / "confirmed.json").exists():
        log("confirm: confirmed.json is not of this body log at this step with these settings, "
            "so the bodies are confirmed again")
    record["confirm_note"] = confirm_skipped(cfg)
    if record["confirm_note"]:
        if n:  # --confirm 0 said so itself
            log(f"confirm: {record['confirm_note']}")
        return record, None, None
    path = out / "bodies.sqlite"
    ranked = bodylog.best_bodies(path, n)
    shapes = bodylog.shapes(path, p.space, [b["body"] for b in ranked])
    missing = [b["body"] for b in ranked if b["body"] not in shapes]
    if missing:  # every run that can reach this stage keeps each body's shape in its log
        raise checkpoints.Damaged(f"{path}: no shape kept for the body log's "
                                  f"{', '.join(missing)} (a damaged log): the run cannot "
                                  "confirm it")
    also = "" if not greedy else f", with the greedy trajectory's {len(greedy)} bodies"
    log(f"confirm: the {len(ranked)} bodies of the highest mean{also}, {c} fresh evaluations "
        "each...")
    key = jax.random.fold_in(jax.random.PRNGKey(cfg.seed), CONFIRM_SALT)
    bodies = [shapes[b["body"]] for b in ranked] + list(greedy or [])
    morphs = jax.tree.map(lambda *x: np.stack(x), *bodies)
    every = confirm(p.space, morphs, key, p.fitness, c, ranked=False)
    found, joined = rank(every[:len(ranked)]), every[len(ranked):]
    in_log = {b["body"]: b for b in ranked}
    record["confirmed"] = [confirmed_entry(f, in_log[f.body]) for f in found]
    record["confirm_note"] = (
        f"the {len(found)} bodies of the highest mean in the body log, each evaluated again {c} "
        "times from scratch (fresh keys and controllers, no inheritance) in one fitness call; "
        f"mean and 95% Student-t interval over the {c}"
    )
    if greedy:  # the greedy trajectory's, for a --resume to keep (`kept_greedy`)
        record["greedy"] = [{"body": f.body, "mean": f.mean,
                             "values": [float(v) for v in f.values]} for f in joined]
    return record, found[0], None if greedy is None else joined


def greedy_confirmed(greedy: Greedy, joined: list[Confirmed]) -> Greedy:
    """The walked `greedy` with its bodies' results `joined` from the confirm stage's call: each
    body's fitness the mean over its C fresh controllers, its controllers best first."""
    return greedy._replace(fitness=[f.mean for f in joined],
                           params=[best_first(f) for f in joined],
                           controllers=len(joined[0].values), confirmed=True)


def best_first(found: Confirmed):
    """The C controllers of `found`, best first (best.gif replays the 0th; ties in their
    order); None where the fitness trains none."""
    if found.params is None:
        return None
    order = np.argsort(-found.values, kind="stable")
    return jax.tree.map(lambda x: x[order], found.params)


def confirmed_entry(found: Confirmed, logged: dict) -> dict:
    """confirmed.json's (and summary.json's) entry of a confirmed body, with its mean and count
    in the body log."""
    return {
        "body": found.body,
        "mean": found.mean,
        "ci95": list(found.ci95),
        "controllers": len(found.values),
        "values": [float(v) for v in found.values],
        "diverged": int(found.diverged.sum()),
        "log_mean": logged["mean_fitness"],
        "log_evaluations": logged["evaluations"],
        **gait_entry(found),
    }


def gait_entry(found: Confirmed) -> dict:
    """A confirmed body's gait over its fresh evaluations: mean distance (m) and upright (the
    fraction of an episode before a fall), the fraction of evaluations upright the whole
    episode, and each evaluation's; None where the fitness measures no gait."""
    if not np.isfinite(found.distance).all():
        return {"distance": None, "upright": None, "upright_whole": None}
    return {
        "distance": float(found.distance.mean()),
        "upright": float(found.upright.mean()),
        "upright_whole": found.upright_whole,
        "distances": [round(float(d), 4) for d in found.distance],
        "uprights": [round(float(u), 4) for u in found.upright],
    }


def reported_best(out: Path, p: Pipeline, record: dict, top: Confirmed | None, draw: tuple):
    """The body a run reports as its best: (morph, fitness, controllers, their fitness config),
    chosen here alone.

    The confirmed best `top` with its C fresh controllers, best first (best.gif replays the
    0th); else the best of `record` confirmed when the run first finished (its controllers read
    back from controllers/best); else, nothing confirmed, `draw`: the highest single draw's
    (morph, fitness, controllers).
    """
    if top is not None:
        params = best_first(top)
        cfg = p.fitness if params is None else p.fitness.with_controllers(len(top.values))
        return top.morph, top.mean, params, cfg
    if record["confirmed"]:
        morph = Morphology.from_dict(record["best_morphology"])
        if not saved_controllers.has_controllers(p.fitness):
            return morph, record["confirmed"][0]["mean"], None, p.fitness
        kept = saved_controllers.load(out / saved_controllers.DIR / "best")
        return morph, record["confirmed"][0]["mean"], kept.params, kept.fitness
    return (*draw, p.fitness)


def save_controllers(out: Path, p: Pipeline, seed: int, best, best_fitness: float, best_params,
                     greedy: Greedy | None, best_cfg=None) -> list[str]:
    """controllers/best and controllers/stepT for the evaluated greedy trajectory's bodies, for
    a fitness that trains controllers; every process calls it. best_cfg: the fitness config the
    best body's controllers were trained under (default the run's; the confirm stage's has C
    controllers); the greedy bodies' has `greedy.controllers` (None: the run's). Returns the
    names saved."""
    if not saved_controllers.has_controllers(p.fitness):
        return []
    bodies = [("best", best, best_params, best_fitness, best_cfg or p.fitness)]
    if greedy is not None:
        k = greedy.controllers
        greedy_cfg = p.fitness if k is None else p.fitness.with_controllers(k)
        bodies += [(f"step{t}", m, params, f, greedy_cfg) for t, (m, params, f)
                   in enumerate(zip(greedy.morphs, greedy.params, greedy.fitness))]
    for name, morph, params, fitness, fit_cfg in bodies:
        if params is None and name != "best":  # kept from the first finish (`kept_greedy`)
            continue
        label = name if name == "best" else f"step {name[4:]}"
        saved = saved_controllers.SavedController(p.space, fit_cfg, seed, morph, params, fitness,
                                                  label)
        saved_controllers.save(out / saved_controllers.DIR / name, saved)
    return [name for name, *_ in bodies]
