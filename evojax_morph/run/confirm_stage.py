"""A run's confirm stage: the bodies of the highest mean in its body log confirmed, the greedy
trajectory's bodies evaluated (in the same fitness call where it confirms now), and the body the
run reports as its best chosen, by the library's confirm (`search.confirm`: `confirm_record`,
`reported_best`); the stage waits for its compiled program, times it, hands the report stage a
`Best`, and the recorder confirmed.json and the controllers of the best body and of the greedy
trajectory.
"""

from __future__ import annotations

from typing import NamedTuple

from evojax_morph.fitnesses import FitnessConfig
from evojax_morph.fitnesses.batched import lower_evaluate
from evojax_morph.morphology import Morphology
from evojax_morph.run.compile_ahead import Job
from evojax_morph.run.resume import Start
from evojax_morph.search.confirm import (
    Confirmed,
    confirm_record,
    greedy_bodies,
    greedy_confirmed,
    kept_greedy,
    reported_best,
    save_controllers,
)
from evojax_morph.search.pipeline import Greedy
from evojax_morph.sharding import to_host


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
            begin.kept, begin.stale, run.log)
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