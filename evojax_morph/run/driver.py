"""The host side of a run: the outer Python loop over jitted chunks, with its files.

`execute(cfg, out, resume)` runs `pipeline.build(cfg)` chunk by chunk and writes the run
directory (`evojax_morph.run` lists its files), as stages each handing its results to the next:
`_build`, `_warm_up` (m0 or a checkpoint, `checkpoints`), `_evolve` (the steps, then the greedy
rollout), `_confirm` (`confirm_stage`: the bodies of the highest mean in the body log evaluated
again from scratch; its best is the run's best body) and `report.report_stage`. Each stage
offers the programs it will call, which compile ahead (`compile_ahead`).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np

from evojax_morph.fitnesses import get_fitness
from evojax_morph.morphology import Morphology
from evojax_morph.physics.engines import registered
from evojax_morph.run import bodylog, checkpoints, saved_controllers, video
from evojax_morph.run.compile_ahead import Warmup
from evojax_morph.run.confirm import Confirmed, confirm, lower_confirm
from evojax_morph.run.pipeline import Greedy, Pipeline, RunConfig, build, make_greedy_rollout
from evojax_morph.run.report import confirmed_entry, report_stage
from evojax_morph.sharding import barrier, batch_mesh, replicated, to_host

CONFIRM_SALT = 0x636F6E66  # the confirm stage's key: fold_in(PRNGKey(seed), CONFIRM_SALT)


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
    # Lowered on the warmup thread while m0 compiles and runs, and compiled there unless the
    # engine captures graphs on a GPU (MuJoCo Warp), which a compile's autotuning breaks
    # (`warmup`); on several GPUs then not even lowered ahead (runs there hung; `warmup`).
    graphs = registered(cfg.physics).graph_capture and jax.default_backend() == "gpu"
    ahead = Warmup(on=False if graphs and jax.device_count() > 1 else None, compiles=not graphs)
    try:
        _execute(cfg, out, resume, gif, ahead)
    finally:
        ahead.close(wait=False)  # on an error, drops the programs not begun


class Clock:
    """The wall clock of a run's phases, from its start, for timing.json."""

    def __init__(self):
        self.started = self.last = time.perf_counter()
        self.phases = {}  # name: seconds since the phase before

    def phase(self, name: str) -> None:
        now = time.perf_counter()
        self.phases[name] = round(now - self.last, 1)
        self.last = now


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
    greedy_rollout: Callable | None  # None for the baselines: no policy to roll out
    key_init: jax.Array
    key_greedy: jax.Array


class Evolved(NamedTuple):
    """What the evolve stage hands down: the agent state after `step` steps, its record, and
    the trained agent's greedy rollout."""

    state: object
    step: int
    rows: list[dict]  # metrics.csv's
    chunk_seconds: list[tuple[int, float]]  # (steps, wall clock) of each chunk; the first compiles
    dispatch: float | None  # seconds until the first chunk call returns (`timing`)
    greedy: Greedy | None  # None for the baselines: no policy to roll out


class Best(NamedTuple):
    """What the confirm stage hands down: the body the run reports as its best, and the rest."""

    morph: Morphology
    fitness: float
    record: dict  # confirmed.json's
    top: Confirmed | None  # the confirmed best, when evaluated now
    saved: list[str]  # the controllers saved


def _execute(cfg: RunConfig, out: Path, resume: bool, gif: bool, ahead: Warmup) -> None:
    """The run as stages: build, warm up (m0 or a checkpoint), evolve, confirm, report."""
    clock = Clock()
    run, step, state, abstract = _build(cfg, out, resume, gif)
    compile_ahead(ahead, _evolve_jobs(run, abstract, step or 0) + _confirm_jobs(run)
                  + _report_jobs(run))  # queued before m0's evaluation, begun after its lowering
    step, state, rows = _warm_up(run, step, state, ahead)
    clock.phase("build_and_m0")
    evolved = _evolve(run, step, state, rows, ahead, clock)
    best = _confirm(run, evolved, ahead, clock)
    if run.lead:
        report_stage(run, evolved, best, clock)


def _build(cfg: RunConfig, out: Path, resume: bool, gif: bool):
    """The pipeline and the newest checkpoint that reads if `resume`; returns (Run, step, state,
    abstract), step and state None where no checkpoint was restored, abstract the agent state's
    shapes and placement (what the later programs are compiled for)."""
    lead = jax.process_index() == 0
    write_config = lambda: (out / "config.json").write_text(  # noqa: E731
        json.dumps(dataclasses.asdict(cfg), indent=1))
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
    step = state = None
    if resume:
        step, state, _ = checkpoints.restore_newest(
            out, lambda manager, step: checkpoints.restore_checked(manager, step, abstract), log
        )
        if lead:  # a checkpoint reads (or there is none): the run goes on under this config
            write_config()
    _, manager = checkpoints.checkpoint_manager(out)
    bodies = bodylog.BodyLog(out / "bodies.sqlite", p.space) if lead else None
    greedy_rollout = None if p.agent.scores is None else make_greedy_rollout(p)
    run = Run(cfg, out, gif, p, lead, log, manager, bodies, greedy_rollout, key_init, key_greedy)
    return run, step, state, abstract


def _warm_up(run: Run, step, state, ahead: Warmup):
    """The run's start: the restored `state` at `step` with metrics.csv's rows up to it, or
    (`step` None) m0 evaluated in every evolution, at step 0. Returns (step, state, rows)."""
    if step is not None:
        ahead.start()
        with open(run.out / "metrics.csv") as f:
            rows = [r for r in csv.DictReader(f) if int(r["step"]) <= step]
        if run.lead:
            run.bodies.truncate(step)
        run.log(f"resumed at step {step}")
        return step, state, rows
    run.log("evaluating m0 in every evolution...")
    m0 = run.p.agent.init.lower(run.key_init)
    ahead.start()  # after m0's lowering: the two would take turns at the GIL
    state = m0.compile()(run.key_init)
    first = to_host(state.first)
    if run.lead:
        run.bodies.truncate(-1)
        run.bodies.add(0, first.morph, first.fitness, first.fitness_std, first.diverged,
                       distance=first.distance, upright=first.upright)
        run.bodies.commit()
    return 0, state, []


def _evolve(run: Run, step: int, state, rows: list[dict], ahead: Warmup, clock: Clock) -> Evolved:
    """The steps from `step` to cfg.steps, chunk by chunk: metrics.csv, the body log and
    TensorBoard after each chunk, a checkpoint every cfg.checkpoint_every chunks and at the end;
    then the trained agent's greedy rollout (an agent with a policy)."""
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
            with open(run.out / "metrics.csv", "w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=list(rows[0]))
                w.writeheader()
                w.writerows(rows)
        if chunks_done % cfg.checkpoint_every == 0 or step >= cfg.steps:
            run.manager.save(step, args=checkpoints.save_args(state))
    bar.close()
    run.manager.wait_until_finished()
    if lead:
        writer.close()
        run.bodies.close()
    clock.phase("steps")
    greedy = None
    if run.greedy_rollout is not None:
        ahead.wait("greedy")
        greedy = run.greedy_rollout(state.learner, state.first, run.key_greedy)
    barrier("body log written")  # every process reads it in the confirm stage
    clock.phase("greedy_rollout")
    return Evolved(state, step, rows, chunk_seconds, dispatch, greedy)


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


def _confirm(run: Run, evolved: Evolved, ahead: Warmup, clock: Clock) -> Best:
    """The confirm stage, the best body's and the greedy trajectory's controllers saved, and
    confirmed.json (if confirmed now, lead process); every process calls it."""
    p, cfg, state = run.p, run.cfg, evolved.state
    best, best_fitness, best_params = to_host(
        (state.best_morph, state.best_fitness, state.best_params)
    )
    ahead.wait("confirm")
    record, top = confirm_stage(run.out, p, cfg, evolved.step, run.log)
    clock.phase("confirm")
    ahead.close()  # best.gif's replay and GL
    best, best_fitness, best_params, best_cfg = reported_best(
        run.out, p, record, top, (best, float(best_fitness), best_params)
    )
    saved = save_controllers(run.out, p, cfg.seed, best, best_fitness, best_params,
                             evolved.greedy, best_cfg)
    clock.phase("controllers")
    if top is not None and run.lead:  # written last: the stage is done, a --resume keeps it
        record["best_morphology"] = best.to_dict()
        (run.out / "confirmed.json").write_text(json.dumps(checkpoints.seal(record), indent=1))
    return Best(best, best_fitness, record, top, saved)


class Job(NamedTuple):
    """A job a stage offers to do ahead (`warmup`): `fn` lowers a program of its, compiled on
    the compiling thread in the order given; or, `own_thread`, a probe on a thread of its own."""

    name: str
    fn: Callable
    own_thread: bool = False


def compile_ahead(ahead: Warmup, jobs: list[Job]) -> None:
    """Gives `ahead` the jobs the stages offer: it only collects them."""
    for job in jobs:
        (ahead.run if job.own_thread else ahead.compile)(job.name, job.fn)


def _evolve_jobs(run: Run, state, start: int) -> list[Job]:
    """The chunks of the sizes the steps from `start` take, then the greedy rollout."""
    cfg, p = run.cfg, run.p
    sizes = [min(cfg.chunk, cfg.steps - s) for s in range(start, cfg.steps, cfg.chunk)]
    jobs = [Job(f"chunk {n}", lambda n=n: p.agent.chunk.lower(state, n))
            for n in dict.fromkeys(sizes)]
    if run.greedy_rollout is not None:
        jobs.append(Job("greedy", lambda: run.greedy_rollout.lower(state.learner, state.first,
                                                                   run.key_greedy)))
    return jobs


def _confirm_jobs(run: Run) -> list[Job]:
    """The confirm stage's one fitness call, where it makes one."""
    cfg, p = run.cfg, run.p
    return [] if confirm_skipped(cfg) else [Job("confirm", lambda: lower_confirm(
        p.space, cfg.confirm, p.fitness, cfg.confirm_controllers))]


def _report_jobs(run: Run) -> list[Job]:
    """best.gif's replay (of the controllers `reported_best` leaves) and its GL probes."""
    cfg, p = run.cfg, run.p
    if not (run.gif and run.lead):
        return []
    shown = p.fitness if confirm_skipped(cfg) else p.fitness.with_controllers(
        cfg.confirm_controllers)
    return [Job("replay", lambda: video.lower_replay(p.space, shown)),
            Job("gl", video.choose_gl, own_thread=True)]


def reported_best(out: Path, p: Pipeline, record: dict, top: Confirmed | None, draw: tuple):
    """The body a run reports as its best: (morph, fitness, controllers, their fitness config).

    The confirmed best `top` with its C fresh controllers, best first (best.gif replays the
    0th); else the best of `record` confirmed when the run first finished (its controllers read
    back from controllers/best); else, nothing confirmed, `draw`: the highest single draw's
    (morph, fitness, controllers).
    """
    if top is not None:
        params, cfg = None, p.fitness
        if top.params is not None:
            order = np.argsort(-top.values, kind="stable")
            params = jax.tree.map(lambda x: x[order], top.params)
            cfg = p.fitness.with_controllers(len(top.values))
        return top.morph, top.mean, params, cfg
    if record["confirmed"]:
        morph = Morphology.from_dict(record["best_morphology"])
        if not saved_controllers.has_controllers(p.fitness):
            return morph, record["confirmed"][0]["mean"], None, p.fitness
        kept = saved_controllers.load(out / saved_controllers.DIR / "best")
        return morph, record["confirmed"][0]["mean"], kept.params, kept.fitness
    return (*draw, p.fitness)


def confirm_skipped(cfg: RunConfig) -> str | None:
    """Why the confirm stage evaluates nothing (confirmed.json's note), None where it does: the
    one place this is decided (`_confirm_jobs`, `confirm_stage`)."""
    if cfg.confirm == 0:
        return "not run (--confirm 0): the best body is the highest single draw, a noisy maximum"
    if get_fitness(cfg.fitness).deterministic:
        return (f"not run: the {cfg.fitness} fitness is deterministic, so an evaluation again "
                "gives the same values; the best body is the highest single draw")
    return None


def confirm_stage(out: Path, p: Pipeline, cfg: RunConfig, step: int, log=print):
    """The run's confirm stage; every process calls it, after the body log is written.

    The `cfg.confirm` distinct bodies of the highest mean in the body log (`bodylog.
    best_bodies`: ties to the body evaluated more often, then to the one seen first) are each
    evaluated `cfg.confirm_controllers` times from scratch, in one fitness call (`confirm`):
    fresh controllers, no inheritance, keys from `fold_in(PRNGKey(seed), CONFIRM_SALT)`, which
    no other part of the run uses. Skipped, with a note saying why (`confirm_skipped`); not done
    again when confirmed.json says it was done at this step with these settings (a --resume of
    a finished run).

    Returns:
      (record, top): record is what confirmed.json keeps (env_steps, bodies, controllers,
      "confirmed": summary entries best first, "confirm_note"); top is the best `Confirmed`
      when it was evaluated now, else None.
    """
    n, c = cfg.confirm, cfg.confirm_controllers
    record = {"env_steps": step, "bodies": n, "controllers": c, "confirmed": []}
    done = out / "confirmed.json"
    if done.exists():
        before = checkpoints.read_sealed(done)
        if all(before.get(k) == record[k] for k in ("env_steps", "bodies", "controllers")):
            log("confirm: done when the run finished, kept (confirmed.json)")
            return before, None
    record["confirm_note"] = confirm_skipped(cfg)
    if record["confirm_note"]:
        if n:  # --confirm 0 said so itself
            log(f"confirm: {record['confirm_note']}")
        return record, None
    path = out / "bodies.sqlite"
    ranked = bodylog.best_bodies(path, n)
    shapes = bodylog.shapes(path, p.space, [b["body"] for b in ranked])
    ranked = [b for b in ranked if b["body"] in shapes]  # bodies of a run begun before shapes
    log(f"confirm: the {len(ranked)} bodies of the highest mean, {c} fresh evaluations each...")
    key = jax.random.fold_in(jax.random.PRNGKey(cfg.seed), CONFIRM_SALT)
    morphs = jax.tree.map(lambda *x: np.stack(x), *[shapes[b["body"]] for b in ranked])
    found = confirm(p.space, morphs, key, p.fitness, c)
    in_log = {b["body"]: b for b in ranked}
    record["confirmed"] = [confirmed_entry(f, in_log[f.body]) for f in found]
    record["confirm_note"] = (
        f"the {len(found)} bodies of the highest mean in the body log, each evaluated again {c} "
        "times from scratch (fresh keys and controllers, no inheritance) in one fitness call; "
        f"mean and 95% Student-t interval over the {c}"
    )
    return record, found[0]


def save_controllers(out: Path, p: Pipeline, seed: int, best, best_fitness: float, best_params,
                     greedy: Greedy | None, best_cfg=None) -> list[str]:
    """controllers/best and controllers/stepT for the greedy trajectory's bodies, for a fitness
    that trains controllers; every process calls it. best_cfg: the fitness config the best
    body's controllers were trained under (default the run's; the confirm stage's has C
    controllers). Returns the names saved."""
    if not saved_controllers.has_controllers(p.fitness):
        return []
    bodies = [("best", best, best_params, best_fitness, best_cfg or p.fitness)]
    if greedy is not None:
        bodies += [(f"step{t}", m, params, f, p.fitness) for t, (m, params, f)
                   in enumerate(zip(greedy.morphs, greedy.params, greedy.fitness))]
    for name, morph, params, fitness, fit_cfg in bodies:
        label = name if name == "best" else f"step {name[4:]}"
        saved = saved_controllers.SavedController(p.space, fit_cfg, seed, morph, params, fitness,
                                            label)
        saved_controllers.save(out / saved_controllers.DIR / name, saved)
    return [name for name, *_ in bodies]
