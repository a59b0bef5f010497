"""A run's evolve stage: from m0 (or a restored checkpoint) the steps, chunk by chunk, then the
trained agent's greedy walk from m0; it hands the confirm stage an `Evolved`."""

from __future__ import annotations

import sys
import time
from typing import NamedTuple

from evojax_morph.run.compile_ahead import Job
from evojax_morph.run.resume import Start
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
