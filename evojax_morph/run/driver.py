"""The host side of a run: its stages, each handing its results to the next in memory.

`execute(cfg, out, resume)` builds the run (`pipeline.build`), opens its directory with the
`Recorder`, which reads where the run starts before it writes anything (m0, or with `resume` its
newest checkpoint: `resume.start`, the one place the run reads its own directory), then runs
its three stages (`stages`): `Evolve` (the steps chunk by chunk, then the trained agent's
greedy walk from m0) -> `Evolved`; `Confirm` (the bodies of the highest mean in the body log
evaluated again from scratch, the greedy trajectory's in the same call; its best is the run's
best body) -> `Best`; `Report`. Each stage offers the programs it will call through one method,
`programs()`, which compile ahead on a second thread (`compile_ahead`), and runs with
`run_stage`. One `Recorder` writes every file (`evojax_morph.run` lists them).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import jax

from evojax_morph.records import checkpoints, saved_controllers
from evojax_morph.run.compile_ahead import Warmup
from evojax_morph.run.recorder import Recorder
from evojax_morph.run.stages import Confirm, Evolve, Report
from evojax_morph.search.pipeline import Pipeline, RunConfig, build
from evojax_morph.sharding import batch_mesh, replicated


def fresh_run_dir(cfg: RunConfig) -> Path:
    """runs/SPACE-FITNESS-seedS, or the first of -2, -3, ... that does not exist yet."""
    base = Path("runs") / f"{cfg.space}-{cfg.fitness}-seed{cfg.seed}"
    out, n = base, 1
    while out.exists():
        n += 1
        out = base.with_name(f"{base.name}-{n}")
    return out


def execute(cfg: RunConfig, out: Path, resume: bool, gif: bool = True) -> None:
    """Runs `cfg` in the directory `out` (checked writable), from its last checkpoint if
    `resume`, drawing best.gif at the end if `gif`; every process calls it, process 0 writes
    the files and prints. The run as stages: build, evolve (from m0 or a checkpoint), confirm,
    report; the programs called after m0's compile ahead (`compile_ahead`), each stage's queued
    before m0's evaluation (begun after its lowering)."""
    clock = Clock()
    record = Recorder(out, lead=jax.process_index() == 0)
    run, abstract = _build(cfg, out, gif)
    begin = record.open(run, resume, abstract)  # read back first, then written
    clock.part("build")
    # Each stage's programs queued for compiling ahead; on leaving, an error's too, the warmup
    # drops those not begun.
    with Warmup.for_engine(run.p.engine, clock.waits) as ahead:
        evolve = Evolve(run, begin, abstract)
        ahead.collect(evolve.programs())
        confirm = Confirm(run, begin)
        ahead.collect(confirm.programs())
        report = Report(run, confirm.shown)
        ahead.collect(report.programs())
        try:
            with checkpoints.saving(out / "checkpoints"):
                evolved = evolve.run_stage(record, ahead, clock)
                best = confirm.run_stage(evolved, record, ahead, clock)
                if run.lead:
                    report.run_stage(evolved, best, record, clock)
        except OSError:  # a full disk, a folder made read-only: the checkpoints in flight land
            with contextlib.suppress(Exception):  # first, so the run resumes from the newest
                record.manager.wait_until_finished()
            raise


class Clock:
    """The wall clock of a run's phases, from its start, for timing.json; and of parts within a
    phase, and the main thread's waits for the compile-ahead jobs, to say where a phase goes."""

    def __init__(self):
        self.started = self.last = self.mark = time.perf_counter()
        self.phases = {}  # name: seconds since the phase before
        self.parts = {}  # name: seconds since the part or phase before
        self.waits = {}  # `Warmup.waited`: job name: seconds

    def phase(self, name: str) -> None:
        now = time.perf_counter()
        self.phases[name] = round(now - self.last, 1)
        self.last = self.mark = now

    def part(self, name: str) -> None:
        now = time.perf_counter()
        self.parts[name] = round(now - self.mark, 2)
        self.mark = now


class Run(NamedTuple):
    """What every stage reads: the run's settings and parts, built once."""

    cfg: RunConfig
    out: Path
    gif: bool  # best.gif: asked for, and the fitness trains controllers (decided once)
    p: Pipeline
    lead: bool  # the process that writes files and prints
    log: Callable  # print on the lead process, else nothing
    key_init: jax.Array
    key_greedy: jax.Array


def _build(cfg: RunConfig, out: Path, gif: bool) -> tuple[Run, object]:
    """The run's parts, and the agent state's shapes and placement (where a checkpoint is
    restored to, what the later programs are compiled for)."""
    lead = jax.process_index() == 0
    p = build(cfg)
    gif = gif and saved_controllers.has_controllers(p.fitness)  # asked, and a controller to show
    log = print if lead else (lambda *a, **k: None)
    log(f"evojax_morph: {cfg.agent} on {cfg.space} with {cfg.fitness} fitness, {cfg.num_envs} "
        f"parallel evolutions x {cfg.steps} steps, horizon {p.env.horizon}, on "
        f"{jax.device_count()} {jax.default_backend()} device(s) in {jax.process_count()} "
        f"process(es); run in {out}")
    key_init, key_greedy = jax.random.split(jax.random.PRNGKey(cfg.seed))
    on_mesh = lambda x: jax.ShapeDtypeStruct(  # noqa: E731
        x.shape, x.dtype, sharding=replicated(batch_mesh()), weak_type=x.weak_type)
    abstract = jax.tree.map(on_mesh, jax.eval_shape(p.agent.init, key_init))
    return Run(cfg, out, gif, p, lead, log, key_init, key_greedy), abstract
