"""A run's three stages, in the order they run, each handing the next a value in memory:
`Evolve` (from m0 or a restored checkpoint the steps, chunk by chunk, then the trained agent's
greedy walk from m0) -> `Evolved`; `Confirm` (the bodies of the highest mean in the body log
evaluated again from scratch, the greedy trajectory's in the same fitness call, and the body the
run reports as its best chosen, by the library's confirm: `search.confirm`) -> `Best`; `Report`
(summary.json, the plots, best.gif and timing.json, from what `report` makes of the two).

Each stage offers the programs it will call through one method, `programs()`, which compile
ahead on a second thread (`compile_ahead`), and runs with `run_stage`: it waits for its
programs, times its phases on the run's clock (`driver.Clock`) and hands its results to the
`Recorder`, which writes the files.
"""

from __future__ import annotations

import sys
import time
from typing import NamedTuple

from evojax_morph.figures import video
from evojax_morph.fitnesses import FitnessConfig
from evojax_morph.fitnesses.batched import lower_evaluate
from evojax_morph.morphology import Morphology
from evojax_morph.run.compile_ahead import Job
from evojax_morph.run.report import timing, where, write_results
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
from evojax_morph.search.loop import chunks
from evojax_morph.search.pipeline import Greedy
from evojax_morph.sharding import batch_mesh, to_host


class Evolved(NamedTuple):
    """What the evolve stage hands down: the agent state after `step` steps, the trained
    agent's greedy walk (its bodies not yet evaluated), and what the body log says."""

    state: object
    step: int
    chunk_seconds: list[tuple[int, float]]  # (steps, wall clock) of each chunk; the first compiles
    dispatch: float | None  # seconds until the first chunk call returns (`report.timing`)
    greedy: Greedy | None  # walked, no fitness yet; None for the baselines: no policy
    best_bodies: list[dict]  # the body log's 10 of the highest mean
    best_draw: dict  # the body log's highest single draw
    log: dict  # the body log's proof at `step` (confirmed.json keeps it)
    candidates: list  # (entry, shape JSON) of the bodies to confirm, best first (`Recorder`)


class Evolve:
    """The evolve stage of `run` (`driver.Run`) from `start`, its agent state of the shapes
    and placement `abstract`."""

    def __init__(self, run, start: Start, abstract):
        self.run, self.start, self.abstract = run, start, abstract
        self.walk = run.p.greedy_walk  # None for the baselines: no policy to roll out
        self.confirm = run.cfg.confirm if start.confirms else 0  # bodies it takes from the log

    def programs(self) -> list[Job]:
        """The chunks of the sizes the steps take, then the greedy walk."""
        cfg, agent, state = self.run.cfg, self.run.p.agent, self.abstract
        first = self.start.step or 0
        sizes = [min(cfg.chunk, cfg.steps - s) for s in range(first, cfg.steps, cfg.chunk)]
        jobs = [Job(f"chunk {n}", lambda n=n: agent.chunk.lower(state, n))
                for n in dict.fromkeys(sizes)]
        if self.walk is not None:
            jobs.append(Job("greedy", lambda: self.walk.lower(state.learner, state.first,
                                                              self.run.key_greedy)))
        return jobs

    def run_stage(self, record, ahead, clock) -> Evolved:
        """The steps from the start to cfg.steps: the `record`er gets each chunk's results and
        a checkpoint every cfg.checkpoint_every chunks and at the end; then the greedy walk."""
        from tqdm import tqdm

        run, cfg = self.run, self.run.cfg
        step, state, loading = self._begin(record, ahead, clock)
        clock.phase("build_and_m0")
        bar = tqdm(total=cfg.steps, initial=min(step, cfg.steps), unit="step",
                   dynamic_ncols=True, file=sys.stdout, disable=not run.lead)
        chunk_seconds, dispatch = [], None

        def program(n):  # compiled ahead; a resumed run's first call after the engine's preload
            nonlocal loading
            ahead.wait(f"chunk {n}")
            if loading is not None:
                waited = time.perf_counter()
                loading.result()
                clock.waits["preload"], loading = round(time.perf_counter() - waited, 2), None
            return lambda state: run.p.agent.chunk(state, n)

        for done in chunks(program, state, step, cfg.steps, cfg.chunk):
            state, step = done.state, done.step
            dispatch = round(done.dispatch, 2) if dispatch is None else dispatch
            chunk_seconds.append((done.n, done.seconds))
            record.chunk(step - done.n, done.metrics)
            bar.update(done.n)
            bar.set_postfix(reward=f"{record.rows[-1]['reward_median']:.3g}",
                            best=f"{record.rows[-1]['best_fitness']:.3g}")
            if len(chunk_seconds) % cfg.checkpoint_every == 0 or step >= cfg.steps:
                record.checkpoint(step, state)
        bar.close()
        told = record.end_of_steps(self.confirm)
        clock.phase("steps")
        greedy = None
        if self.walk is not None:
            ahead.wait("greedy")
            greedy = self.walk(state.learner, state.first, run.key_greedy)
        clock.phase("greedy_walk")  # the walk alone; its bodies are evaluated in "confirm"
        return Evolved(state, step, chunk_seconds, dispatch, greedy, told["best_bodies"],
                       told["best_draw"], told["log"], told["candidates"])

    def _begin(self, record, ahead, clock):
        """The restored state at its step, or (no checkpoint) m0 evaluated in every evolution
        at step 0, its lowering, compiling (or loading), the wait for the engine's preload
        (`Engine.preload`) and evaluation timed as the `clock`'s parts. Returns (step, state,
        the preload still to wait for before the first chunk call: a resumed run's, else
        None)."""
        run, begin = self.run, self.start
        preload = run.p.engine.preload
        if begin.step is not None:
            ahead.start()
            loading = preload(batch_mesh().local_devices, run.p.space) if preload else None
            record.begin(begin.step, begin.rows)
            run.log(f"resumed at step {begin.step}")
            return begin.step, begin.state, loading
        run.log("evaluating m0 in every evolution...")
        m0 = run.p.agent.init.lower(run.key_init)
        clock.part("m0_lower")
        # After m0's lowering, as the two would take turns at the GIL: the compile-ahead jobs,
        # and the engine's kernels (Warp's), which compile beside m0's program, not inside it.
        ahead.start()
        loading = preload(batch_mesh().local_devices, run.p.space) if preload else None
        m0 = m0.compile()
        clock.part("m0_compile")
        if loading:
            loading.result()
            clock.part("m0_preload_wait")
        state = m0(run.key_init)
        first = to_host(state.first)
        clock.part("m0_evaluate")
        record.begin(-1, [], first)
        return 0, state, None


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


class Report:
    """The report stage of `run` (`driver.Run`), on the lead process; best.gif replays
    controllers of the fitness config `shown` (those the confirm stage leaves,
    `Confirm.shown`)."""

    def __init__(self, run, shown):
        self.run, self.shown = run, shown

    def programs(self) -> list[Job]:
        """best.gif's replay and its GL probes."""
        run, shown = self.run, self.shown
        if not (run.gif and run.lead):
            return []
        return [Job("replay", lambda: video.lower_replay(run.p.space, shown)),
                Job("gl", video.choose_gl, own_thread=True)]

    def run_stage(self, evolved, best, record, clock) -> None:
        """The report from the earlier stages' results, `evolved` (`Evolved`) and `best`
        (`Best`), and their `clock` (`driver.Clock`): the results
        (`write_results`), then timing.json, through the `record`er."""
        run = self.run
        write_results(run, evolved, best, record, clock.phase)
        times = timing(time.perf_counter() - clock.started, evolved.chunk_seconds) | {
            "phases": clock.phases, "first_chunk_dispatch": evolved.dispatch,
            "chunk_seconds": [round(s, 2) for _, s in evolved.chunk_seconds],
            "parts": clock.parts, "waits": clock.waits, "where": where(run.cfg)}
        record.timing(times)
        if times["step_seconds"]:
            print(f"time: {times['seconds']:.0f} s, {times['step_seconds']:.3g} s a step, "
                  f"{times['outside_steps_seconds']:.0f} s outside the steps (timing.json; "
                  "imports not counted)")
