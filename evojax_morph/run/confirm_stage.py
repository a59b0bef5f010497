"""A run's confirm stage: the bodies of the highest mean in its body log confirmed (`confirm`),
the greedy trajectory's bodies evaluated (in the same fitness call where it confirms now), and
the body the run reports as its best chosen (`reported_best`); it hands the report stage a
`Best`, and the recorder confirmed.json and the controllers of the best body and of the greedy
trajectory.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np

from evojax_morph.fitnesses import FitnessConfig
from evojax_morph.fitnesses.batched import lower_evaluate
from evojax_morph.morphology import Morphology
from evojax_morph.records import saved_controllers
from evojax_morph.run.compile_ahead import Job
from evojax_morph.run.resume import Start, confirm_skipped
from evojax_morph.search.confirm import Confirmed, confirm, rank
from evojax_morph.search.pipeline import Greedy, Pipeline, RunConfig
from evojax_morph.sharding import to_host

CONFIRM_SALT = 0x636F6E66  # the confirm stage's key: fold_in(PRNGKey(seed), CONFIRM_SALT)


class Best(NamedTuple):
    """What the confirm stage hands down: the body the run reports as its best, and the rest."""

    morph: Morphology
    fitness: float
    record: dict  # confirmed.json's
    top: Confirmed | None  # the confirmed best, when evaluated now
    saved: dict  # the controllers saved, by name (None: kept from the first finish)
    greedy: Greedy | None  # the greedy trajectory, evaluated; None for the baselines


class Confirm:
    """The confirm stage of `run` (`driver.Run`) that began at `start`."""

    def __init__(self, run, start: Start):
        self.run, self.start = run, start
        p = run.p  # the fitness config of the controllers `reported_best` leaves (best.gif
        # replays them): the stage's C fresh ones, else (`Start.skipped`) the run's
        self.shown: FitnessConfig = p.fitness if start.skipped else p.fitness.with_controllers(
            run.cfg.confirm_controllers)
        # the greedy bodies' own fitness call: where the stage evaluates nothing now and no
        # kept results of theirs (`kept_greedy`: a finished run resumed keeps them)
        self.apart = run.p.greedy_walk is not None and (start.skipped is not None or (
            start.kept is not None and not start.kept.get("greedy")))

    def programs(self) -> list[Job]:
        """The stage's one fitness call: cfg.confirm bodies and the greedy trajectory's, C
        times each; or the greedy bodies' call of their own."""
        p, cfg = self.run.p, self.run.cfg
        if self.apart:
            return [Job("greedy evaluation", lambda: p.greedy_evaluation.lower(
                self.run.key_greedy))]
        if not self.start.confirms:
            return []
        n = (cfg.confirm + greedy_bodies(p)) * cfg.confirm_controllers
        return [Job("confirm", lambda: lower_evaluate(p.space, n, p.fitness.with_controllers(1)))]

    def run_stage(self, evolved, record, ahead, clock) -> Best:
        """The bodies of the log confirmed with the walked greedy trajectory's in one fitness
        call (`confirm_record`), or, where it confirms nothing now, the greedy trajectory
        evaluated alone; the run's best chosen (`reported_best`), its and the greedy
        trajectory's controllers saved, and confirmed.json written (if confirmed now); every
        process calls it."""
        run, begin = self.run, self.start
        p, cfg, state, greedy = run.p, run.cfg, evolved.state, evolved.greedy
        draw = to_host((state.best_morph, state.best_fitness, state.best_params))
        ahead.wait("confirm")
        record_, top, joined = confirm_record(
            p, cfg, evolved.step, evolved.candidates, None if greedy is None else greedy.morphs,
            begin, run.log)
        if joined is not None:
            greedy = greedy_confirmed(greedy, joined)
        elif greedy is not None:
            greedy = kept_greedy(record_, greedy, p.space)
            if greedy is None:
                ahead.wait("greedy evaluation")
                greedy = p.greedy_evaluation(evolved.greedy, run.key_greedy)
        clock.phase("confirm")
        ahead.close()  # best.gif's replay and GL
        best, best_fitness, best_params, best_cfg = reported_best(
            p, record_, top, (draw[0], float(draw[1]), draw[2]), begin.kept_best)
        saved = save_controllers(p, cfg.seed, best, best_fitness, best_params, greedy, best_cfg)
        record.controllers(saved)
        clock.phase("controllers")
        if top is not None:  # written last: the stage is done, a --resume keeps it
            record_["best_morphology"] = best.to_dict()
            record_["log"] = evolved.log  # whose bodies: a --resume keeps it for this log alone
            record.confirmed(record_)
        return Best(best, best_fitness, record_, top, saved, greedy)


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


def confirm_record(p: Pipeline, cfg: RunConfig, step: int, candidates: list,
                   greedy: list | None = None, start: Start | None = None, log=print):
    """The bodies of a run's log confirmed, the greedy trajectory's `greedy` in the same call;
    every process calls it.

    The `cfg.confirm` distinct bodies of the highest mean in the body log (`candidates`:
    (`bodylog.best_bodies` entry, shape JSON) pairs, best first: ties to the body evaluated
    more often, then to the one seen first), then the bodies `greedy`, are each evaluated
    `cfg.confirm_controllers` times from scratch, in one fitness call (`confirm`): fresh
    controllers, no inheritance, keys from `fold_in(PRNGKey(seed), CONFIRM_SALT)`, which no
    other part of the run uses. The greedy bodies only ride along (one call's latency instead
    of two, issue 61): they enter neither the record nor the choice of the best. Skipped, with a
    note saying why (`Start.skipped`); not done again where confirmed.json was kept from the
    run's finish at this step with these settings and this log (`Start.kept`: a --resume of a
    finished run); `Start.stale`: a confirmed.json that is not is there (it is written again).
    `start`: where the run began (default: from m0 in a new directory).

    Returns:
      (record, top, joined): record is what confirmed.json keeps (env_steps, bodies,
      controllers, "confirmed": summary entries best first, "confirm_note"); top is the best
      `Confirmed` when it was evaluated now, else None; joined the `Confirmed` of each body of
      `greedy`, in its order, when evaluated now, else None.
    """
    n, c = cfg.confirm, cfg.confirm_controllers
    record = {"env_steps": step, "bodies": n, "controllers": c, "confirmed": []}
    start = start or Start(None, None, [], None, None, skipped=confirm_skipped(cfg))
    if start.kept is not None:
        log("confirm: done when the run finished, kept (confirmed.json)")
        return start.kept, None, None
    if start.stale:
        log("confirm: confirmed.json is not of this body log at this step with these settings, "
            "so the bodies are confirmed again")
    record["confirm_note"] = start.skipped
    if record["confirm_note"]:
        if n:  # --confirm 0 said so itself
            log(f"confirm: {record['confirm_note']}")
        return record, None, None
    ranked = [entry for entry, _ in candidates]
    also = "" if not greedy else f", with the greedy trajectory's {len(greedy)} bodies"
    log(f"confirm: the {len(ranked)} bodies of the highest mean{also}, {c} fresh evaluations "
        "each...")
    key = jax.random.fold_in(jax.random.PRNGKey(cfg.seed), CONFIRM_SALT)
    bodies = [p.space.from_json(shape) for _, shape in candidates] + list(greedy or [])
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


def reported_best(p: Pipeline, record: dict, top: Confirmed | None, draw: tuple,
                  kept_best=None):
    """The body a run reports as its best: (morph, fitness, controllers, their fitness config),
    chosen here alone.

    The confirmed best `top` with its C fresh controllers, best first (best.gif replays the
    0th); else the best of `record` confirmed when the run first finished, `kept_best` (its
    body and controllers read back: `Start.kept_best`); else, nothing confirmed, `draw`: the
    highest single draw's (morph, fitness, controllers).
    """
    if top is not None:
        params = best_first(top)
        cfg = p.fitness if params is None else p.fitness.with_controllers(len(top.values))
        return top.morph, top.mean, params, cfg
    if record["confirmed"]:
        morph, saved = kept_best
        if saved is None:  # a fitness that trains no controllers
            return morph, record["confirmed"][0]["mean"], None, p.fitness
        return morph, record["confirmed"][0]["mean"], saved.params, saved.fitness
    return (*draw, p.fitness)


def save_controllers(p: Pipeline, seed: int, best, best_fitness: float, best_params,
                     greedy: Greedy | None, best_cfg=None) -> dict:
    """The controllers of the best body ("best") and of the evaluated greedy trajectory's
    ("stepT"), for a fitness that trains controllers, by name; None for one kept from the
    first finish (`kept_greedy`). best_cfg: the fitness config the best body's controllers
    were trained under (default the run's; the confirm stage's has C controllers); the greedy
    bodies' has `greedy.controllers` (None: the run's)."""
    if not saved_controllers.has_controllers(p.fitness):
        return {}
    bodies = [("best", best, best_params, best_fitness, best_cfg or p.fitness)]
    if greedy is not None:
        k = greedy.controllers
        greedy_cfg = p.fitness if k is None else p.fitness.with_controllers(k)
        bodies += [(f"step{t}", m, params, f, greedy_cfg) for t, (m, params, f)
                   in enumerate(zip(greedy.morphs, greedy.params or [None] * len(greedy.morphs),
                                    greedy.fitness))]
    saved = {}
    for name, morph, params, fitness, fit_cfg in bodies:
        label = name if name == "best" else f"step {name[4:]}"
        saved[name] = None if params is None and name != "best" else (
            saved_controllers.SavedController(p.space, fit_cfg, seed, morph, params, fitness,
                                              label))
    return saved
