"""The host side of a run: the outer Python loop over jitted chunks, with its files.

`execute(cfg, out, resume)` runs `pipeline.build(cfg)` chunk by chunk and writes the run
directory (`evojax_morph.run` lists its files), as stages each handing its results to the next:
`_build`, `_warm_up` (m0 or a checkpoint, `checkpoints`), `_evolve` (the steps, then the greedy
walk from m0), `confirm_stage` (the bodies of the highest mean in the body log evaluated
again from scratch, the greedy trajectory's in the same call; its best is the run's best body)
and `report.report_stage`. Each stage offers the programs it will call, which compile ahead
(`compile_ahead.Warmup.collect`).
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import itertools
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np

from evojax_morph.physics.engines import registered
from evojax_morph.records import bodylog, checkpoints, saved_controllers
from evojax_morph.run.compile_ahead import Job, Warmup
from evojax_morph.run.confirm_stage import (
    best_controllers,
    confirm_jobs,
    confirm_stage,
    greedy_apart,
)
from evojax_morph.run.report import report_jobs, report_stage
from evojax_morph.search.pipeline import (
    Greedy,
    Pipeline,
    RunConfig,
    build,
    make_greedy_evaluation,
    make_greedy_walk,
)
from evojax_morph.sharding import barrier, batch_mesh, replicated, to_host


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
    the files and prints. The programs called after m0's compile ahead (`compile_ahead`)."""
    # Lowered on the compile-ahead thread while m0 compiles and runs, and compiled there unless
    # the engine captures graphs on a GPU (MuJoCo Warp), which a compile's autotuning breaks
    # (`compile_ahead`); on several GPUs then not even lowered ahead (runs there hung).
    graphs = registered(cfg.physics).graph_capture and jax.default_backend() == "gpu"
    ahead = Warmup(on=False if graphs and jax.device_count() > 1 else None, compiles=not graphs)
    try:
        _execute(cfg, out, resume, gif, ahead)
    finally:
        ahead.close(wait=False)  # on an error, drops the programs not begun


class Clock:
    """The wall clock of a run's phases, from its start, for timing.json; and of parts within a
    phase, and the main thread's waits for the compile-ahead jobs, to say where a phase goes."""

    def __init__(self, waits: dict | None = None):
        self.started = self.last = self.mark = time.perf_counter()
        self.phases = {}  # name: seconds since the phase before
        self.parts = {}  # name: seconds since the part or phase before
        self.waits = {} if waits is None else waits  # `Warmup.waited`: job name: seconds

    def phase(self, name: str) -> None:
        now = time.perf_counter()
        self.phases[name] = round(now - self.last, 1)
        self.last = self.mark = now

    def part(self, name: str) -> None:
        now = time.perf_counter()
        self.parts[name] = round(now - self.mark, 2)
        self.mark = now


class Run(NamedTuple):
    """What the build stage hands down to the later ones."""

    cfg: RunConfig
    out: Path
    gif: bool  # best.gif: asked for, and the fitness trains controllers (decided once)
    p: Pipeline
    lead: bool  # the process that writes files and prints
    log: Callable  # print on the lead process, else nothing
    manager: object  # the Orbax CheckpointManager of out/checkpoints
    bodies: bodylog.BodyLog | None  # the body log (lead process only)
    greedy_walk: Callable | None  # None for the baselines: no policy to roll out
    greedy_evaluation: Callable | None  # its bodies evaluated, where the confirm stage does not
    key_init: jax.Array
    key_greedy: jax.Array
    resumed_log: dict | None  # the body log's proof the restored checkpoint holds (None: none)
    resumed_rows: list[dict] | None  # metrics.csv's rows up to the restored checkpoint's step


class Evolved(NamedTuple):
    """What the evolve stage hands down: the agent state after `step` steps, its record, the
    trained agent's greedy walk (its bodies not yet evaluated), and the best of its body log."""

    state: object
    step: int
    rows: list[dict]  # metrics.csv's
    chunk_seconds: list[tuple[int, float]]  # (steps, wall clock) of each chunk; the first compiles
    dispatch: float | None  # seconds until the first chunk call returns (`timing`)
    greedy: Greedy | None  # walked, no fitness yet; None for the baselines: no policy
    best_bodies: list[dict] | None  # the body log's 10 of the highest mean (lead process)
    best_draw: dict | None  # the body log's highest single draw (lead process)
    log: dict | None  # the body log's proof at `step` (lead process; confirmed.json keeps it)


def _execute(cfg: RunConfig, out: Path, resume: bool, gif: bool, ahead: Warmup) -> None:
    """The run as stages: build, warm up (m0 or a checkpoint), evolve, confirm, report."""
    clock = Clock(ahead.waited)
    run, step, state, abstract = _build(cfg, out, resume, gif)
    clock.part("build")
    # The stages' jobs, queued before m0's evaluation, begun after its lowering.
    end = max(step or 0, cfg.steps)  # the step the run ends at
    ahead.collect(_evolve_jobs(run, abstract, step or 0) + confirm_jobs(run, end)
                  + report_jobs(run, best_controllers(cfg, run.p)))
    try:
        with checkpoints.saving(out / "checkpoints"):
            step, state, rows, loading = _warm_up(run, step, state, ahead, clock)
            clock.phase("build_and_m0")
            evolved = _evolve(run, step, state, rows, ahead, clock, loading)
            best = confirm_stage(run, evolved, ahead, clock)
            if run.lead:
                report_stage(run, evolved, best, clock)
    except OSError:  # a full disk, a folder made read-only: the checkpoints in flight land
        with contextlib.suppress(Exception):  # first, so the run resumes from the newest
            run.manager.wait_until_finished()
        raise


def _build(cfg: RunConfig, out: Path, resume: bool, gif: bool):
    """The pipeline and the newest checkpoint that reads if `resume`; returns (Run, step, state,
    abstract), step and state None where no checkpoint was restored, abstract the agent state's
    shapes and placement (what the later programs are compiled for)."""
    lead = jax.process_index() == 0
    write_config = lambda: checkpoints.write_atomic(  # noqa: E731
        out / "config.json", json.dumps(dataclasses.asdict(cfg), indent=1))
    if lead and not resume:
        write_config()
    p = build(cfg)
    gif = gif and saved_controllers.has_controllers(p.fitness)  # asked, and a controller to show
    log = print if lead else (lambda *a, **k: None)
    log(f"evojax_morph: {cfg.agent} on {cfg.space} with {cfg.fitness} fitness, {cfg.num_envs} "
        f"parallel evolutions x {cfg.steps} steps, horizon {p.env.horizon}, on "
        f"{jax.device_count()} {jax.default_backend()} device(s) in {jax.process_count()} "
        f"process(es); run in {out}")

    key = jax.random.PRNGKey(cfg.seed)
    key_init, key_greedy = jax.random.split(key)
    # The agent state's shape and placement: where a checkpoint is restored to, what the later
    # programs are compiled for.
    on_mesh = lambda x: jax.ShapeDtypeStruct(  # noqa: E731
        x.shape, x.dtype, sharding=replicated(batch_mesh()), weak_type=x.weak_type)
    abstract = jax.tree.map(on_mesh, jax.eval_shape(p.agent.init, key_init))
    step = state = resumed_log = rows = None
    if resume:
        step, restored, _ = checkpoints.restore_newest(
            out, lambda manager, step: checkpoints.restore_checked(manager, step, abstract), log
        )
        if step is None:
            log(f"--resume: {out} holds no checkpoint yet (the run stopped before its first), "
                "so it starts again from m0")
        else:
            state, resumed_log = restored[0], restored[1]["log"]
            check_log(out / "bodies.sqlite", step, resumed_log)
            rows = metrics_rows(out / "metrics.csv", step)
        if lead:  # a checkpoint reads (or there is none): the run goes on under this config
            write_config()
    _, manager = checkpoints.checkpoint_manager(out)
    bodies = bodylog.BodyLog(out / "bodies.sqlite", p.space) if lead else None
    walk, evaluation = (None, None) if p.agent.scores is None else (
        make_greedy_walk(p), make_greedy_evaluation(p))
    run = Run(cfg, out, gif, p, lead, log, manager, bodies, walk, evaluation, key_init,
              key_greedy, resumed_log, rows)
    return run, step, state, abstract


def check_log(path: Path, step: int, saved: dict | None) -> None:
    """Raises `checkpoints.Damaged` unless the body log `path` holds, up to `step`, the rows
    whose proof the checkpoint of `step` recorded (`saved`; None: a process that kept no log):
    a log deleted, emptied, cut short, edited or another run's is not resumed."""
    if saved is None:
        return
    with checkpoints.read_error(str(path)):
        found = bodylog.proof(path, step)
    if found != saved:
        what = (f"{found['rows']:,}" if found["rows"] != saved["rows"]
                else "as many, with other values")
        raise checkpoints.Damaged(
            f"--resume: {str(path)!r} is not the body log checkpoint {step} was saved with "
            f"({saved['rows']:,} evaluations up to step {step}; it holds {what}): the run "
            "cannot go on from it (a log changed, damaged or of another run)")


def metrics_rows(path: Path, step: int) -> list[dict]:
    """The rows of steps 1 to `step` of metrics.csv `path`, which a resume from `step` keeps.
    Raises `checkpoints.Damaged` where the file does not hold them whole (deleted, emptied,
    cut short: a run resumed from it would end with rows missing); rows after `step` (the
    steps the resume redoes) may be cut short."""
    with checkpoints.read_error(str(path)), open(path, newline="") as f:
        rows = list(itertools.islice(csv.DictReader(f), step))
    whole = 0  # the rows of steps 1, 2, ... in order, every value there
    for r in rows:
        if None in r or None in r.values() or r.get("step") != str(whole + 1):
            break
        whole += 1
    if whole < step:
        raise checkpoints.Damaged(
            f"--resume: {str(path)!r} does not hold the rows of steps 1 to {step} whole (it "
            f"holds {whole}): the run cannot go on from it (a file changed or damaged)")
    return rows


def _warm_up(run: Run, step, state, ahead: Warmup, clock: Clock):
    """The run's start: the restored `state` at `step` with metrics.csv's rows up to it, or
    (`step` None) m0 evaluated in every evolution, at step 0, its lowering, compiling (or
    loading), the wait for the engine's preload (`Engine.preload`) and evaluation timed as the
    `clock`'s parts. Returns (step, state, rows, the preload still to wait for before the
    first chunk call: a resumed run's, else None)."""
    preload = registered(run.cfg.physics).preload
    if step is not None:
        ahead.start()
        loading = preload(batch_mesh().local_devices, run.p.space) if preload else None
        rows = run.resumed_rows
        if run.lead:
            run.bodies.resume(step)
        run.log(f"resumed at step {step}")
        return step, state, rows, loading
    run.log("evaluating m0 in every evolution...")
    m0 = run.p.agent.init.lower(run.key_init)
    clock.part("m0_lower")
    # After m0's lowering, as the two would take turns at the GIL: the compile-ahead jobs, and
    # the engine's kernels (Warp's), which compile beside m0's program, not inside its call.
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
    if run.lead:
        run.bodies.resume(-1)
        run.bodies.add(0, first.morph, first.fitness, first.fitness_std, first.diverged,
                       distance=first.distance, upright=first.upright)
        run.bodies.commit()
    return 0, state, [], None


def _evolve(run: Run, step: int, state, rows: list[dict], ahead: Warmup, clock: Clock,
            loading=None) -> Evolved:
    """The steps from `step` to cfg.steps, chunk by chunk: metrics.csv, the body log and
    TensorBoard after each chunk, a checkpoint every cfg.checkpoint_every chunks and at the end;
    then the body log's best, and the trained agent's greedy walk (an agent with a policy; the
    confirm stage evaluates its bodies). `loading`: the engine's preload, waited for before the
    first chunk call (timed in the clock's waits as "preload")."""
    from tensorboardX import SummaryWriter
    from tqdm import tqdm

    cfg, lead = run.cfg, run.lead
    writer = SummaryWriter(str(run.out / "tb")) if lead else None
    bar = tqdm(total=cfg.steps, initial=min(step, cfg.steps), unit="step", dynamic_ncols=True,
               file=sys.stdout, disable=not lead)
    chunks_done, chunk_seconds, dispatch = 0, [], None
    while step < cfg.steps:
        n = min(cfg.chunk, cfg.steps - step)
        ahead.wait(f"chunk {n}")
        if loading is not None:
            waited = time.perf_counter()
            loading.result()
            clock.waits["preload"], loading = round(time.perf_counter() - waited, 2), None
        chunk_start = time.perf_counter()
        state, metrics = run.p.agent.chunk(state, n)
        if dispatch is None:  # when the call returns; to_host then waits for the device
            dispatch = round(time.perf_counter() - chunk_start, 2)
        metrics = to_host(metrics)
        chunk_seconds.append((n, time.perf_counter() - chunk_start))
        rows += _record_chunk(run, step, n, metrics, writer)
        step += n
        chunks_done += 1
        bar.update(n)
        bar.set_postfix(reward=f"{rows[-1]['reward_median']:.3g}",
                        best=f"{rows[-1]['best_fitness']:.3g}")
        if lead:
            run.bodies.commit()
            table = io.StringIO(newline="")
            w = csv.DictWriter(table, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
            checkpoints.write_atomic(run.out / "metrics.csv", table.getvalue())
        if chunks_done % cfg.checkpoint_every == 0 or step >= cfg.steps:
            run.manager.save(step, args=checkpoints.save_args(
                state, step, run.bodies.proof() if lead else None))
    bar.close()
    run.manager.wait_until_finished()
    ranked = draw = proof = None
    if lead:
        writer.close()
        proof = run.bodies.proof()
        run.bodies.close()
        path = run.out / "bodies.sqlite"
        ranked, draw = bodylog.best_bodies(path, 10), bodylog.best_draw(path)
    clock.phase("steps")
    greedy = None
    if run.greedy_walk is not None:
        ahead.wait("greedy")
        greedy = run.greedy_walk(state.learner, state.first, run.key_greedy)
    barrier("body log written")  # every process reads it in the confirm stage
    clock.phase("greedy_walk")  # the walk alone; its bodies are evaluated in "confirm"
    return Evolved(state, step, rows, chunk_seconds, dispatch, greedy, ranked, draw, proof)


def _record_chunk(run: Run, step: int, n: int, metrics: dict, writer) -> list[dict]:
    """The `n` steps after `step` of a chunk's host `metrics`: their bodies added to the body
    log and their scalars to TensorBoard (lead process); returns their metrics.csv rows."""
    bodies = metrics.pop("bodies")
    rows = []
    for i in range(n):
        if run.lead:
            at = lambda tree, i=i: jax.tree.map(lambda x: x[i], tree)  # noqa: E731
            run.bodies.add(step + i + 1, at(bodies["morph"]), bodies["fitness"][i],
                           bodies["fitness_std"][i], bodies["diverged"][i],
                           at(bodies["parent"]), bodies["distance"][i], bodies["upright"][i])
        reward = metrics["reward"][i]
        row = {
            "step": step + i + 1,
            "reward_median": float(np.median(reward)),
            "reward_q25": float(np.quantile(reward, 0.25)),
            "reward_q75": float(np.quantile(reward, 0.75)),
            "fitness_mean": float(np.mean(metrics["fitness"][i])),
        }
        row.update({k: float(v[i]) for k, v in metrics.items() if k not in ("reward", "fitness")})
        rows.append(row)
        for name, value in row.items():
            if run.lead and name != "step":
                writer.add_scalar(name.replace("_", "/", 1), value, row["step"])
    return rows


def _evolve_jobs(run: Run, state, start: int) -> list[Job]:
    """The chunks of the sizes the steps from `start` take, then the greedy walk, and its
    bodies' evaluation where the confirm stage's call does not take them (`greedy_apart`)."""
    cfg, p = run.cfg, run.p
    sizes = [min(cfg.chunk, cfg.steps - s) for s in range(start, cfg.steps, cfg.chunk)]
    jobs = [Job(f"chunk {n}", lambda n=n: p.agent.chunk.lower(state, n))
            for n in dict.fromkeys(sizes)]
    if run.greedy_walk is not None:
        apart = greedy_apart(run, max(start, cfg.steps))
        jobs.append(Job("greedy", lambda: [
            run.greedy_walk.lower(state.learner, state.first, run.key_greedy),
            *([run.greedy_evaluation.lower(run.key_greedy)] if apart else [])]))
    return jobs
