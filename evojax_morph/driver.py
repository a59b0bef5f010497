"""The host side of a run: the outer Python loop over jitted chunks, with its files.

`execute(cfg, out, resume)` runs `pipeline.build(cfg)` chunk by chunk and writes the run
directory: config.json, metrics.csv, bodies.sqlite (every body evaluated, `bodylog`),
TensorBoard events (tb/), curve.png, trajectory.png, best.xml, summary.json and Orbax
checkpoints, from which `resume` continues; with the PPO fitness also controllers/ (the trained
controllers of the best body and of the greedy trajectory's, `controllers`) and best.gif (the
best body walking, `video`). At the end the confirm stage (`confirm_stage`) evaluates the
bodies of the highest mean in the body log again from scratch (confirmed.json, confirmed.png);
its best is the run's best body.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

from evojax_morph import bodylog, controllers, plots, video
from evojax_morph.confirm import Confirmed, confirm, lower_confirm
from evojax_morph.fitnesses import get_fitness
from evojax_morph.morphology import Morphology
from evojax_morph.pipeline import Greedy, Pipeline, RunConfig, build, make_greedy_rollout
from evojax_morph.sharding import barrier, batch_mesh, replicated, to_host
from evojax_morph.warmup import Warmup

CONFIRM_SALT = 0x636F6E66  # the confirm stage's key: fold_in(PRNGKey(seed), CONFIRM_SALT)


def checkpoint_manager(out: Path):
    import orbax.checkpoint as ocp

    options = ocp.CheckpointManagerOptions(max_to_keep=2, create=True)
    return ocp, ocp.CheckpointManager(out.resolve() / "checkpoints", options=options)


class ResumeError(RuntimeError):
    """No checkpoint of a run directory could be read back."""


DAMAGED = "checkpoints_damaged"  # where checkpoints that do not read are moved, under the run


def _why(e: Exception) -> str:
    """The first part of a restore error (TensorStore appends its whole spec)."""
    text = str(e).split(" [tensorstore_spec")[0].strip().splitlines()
    text = text[0] if text else ""
    return f"{type(e).__name__}: {text[:300]}"


def _drop_closed_loop_reports() -> None:
    """From now on, drop the "Event loop is closed" reports of reads cut short (idempotent).

    A restore that fails (a damaged array) ends Orbax's event loop while TensorStore still
    reads the checkpoint's other arrays; each read that completes then calls back into the
    closed loop, and Python prints a traceback for it, one per array (about 270 for a run),
    whenever it completes, also after the restore returned. They say nothing the one line
    about the skipped checkpoint does not."""
    previous = sys.unraisablehook
    if getattr(previous, "drops_closed_loop", False):
        return

    def hook(report):
        e = report.exc_value
        if not (isinstance(e, RuntimeError) and str(e) == "Event loop is closed"):
            previous(report)

    hook.drops_closed_loop = True
    sys.unraisablehook = hook


def restore_newest(out: Path, restore_fn, log=print):
    """The state of the newest checkpoint of `out` that reads, newer ones that do not moved
    aside to OUT/checkpoints_damaged/STEP (kept, and out of the way of the steps the resumed
    run saves again).

    Args:
      out: the run directory.
      restore_fn: `restore_fn(manager, step)` -> state; an exception says the step is damaged.
      log: prints what was skipped and why.
    Returns:
      (step, state, [(skipped step, why)]), or (None, None, []) if there is no checkpoint.
    Raises:
      ResumeError: there are checkpoints and none reads; each step's reason is in the message.
    """
    _, manager = checkpoint_manager(out)
    skipped = []
    for step in sorted(manager.all_steps(), reverse=True):
        try:
            state = restore_fn(manager, step)
        except Exception as e:  # damaged data, metadata or a cut-short copy: TensorStore's
            skipped.append((step, _why(e)))  # DATA_LOSS, JSON and file errors alike
            _drop_closed_loop_reports()
            continue
        break
    else:
        if skipped:
            raise ResumeError(
                f"--resume: no checkpoint of {str(out)!r} reads, so there is nothing to resume "
                "from (nothing was changed): " + "; ".join(f"step {s}: {w}" for s, w in skipped)
            )
        return None, None, []
    for bad, why in skipped:
        log(f"checkpoint {bad} does not read, skipped ({why})")
    if skipped:
        if jax.process_index() == 0:
            for bad, _ in skipped:
                target = out / DAMAGED / str(bad)
                n = 1
                while target.exists():
                    n += 1
                    target = out / DAMAGED / f"{bad}-{n}"
                target.parent.mkdir(exist_ok=True)
                (out / "checkpoints" / str(bad)).rename(target)
                log(f"moved it to {target} (kept, not deleted)")
        if jax.process_count() > 1:  # every process sees the moves before it saves
            from jax.experimental import multihost_utils

            multihost_utils.sync_global_devices("damaged checkpoints moved")
    manager.close()
    return step, state, skipped


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
    # Lowered on the warmup thread while m0 compiles and runs, and compiled there unless Warp
    # runs on a GPU, where a compile's autotuning breaks a Warp call's graph capture (`warmup`)
    ahead = Warmup(compiles=not (cfg.physics == "warp" and jax.default_backend() == "gpu"))
    try:
        _execute(cfg, out, resume, gif, ahead)
    finally:
        ahead.close(wait=False)  # on an error, drops the programs not begun


def _execute(cfg: RunConfig, out: Path, resume: bool, gif: bool, ahead: Warmup) -> None:
    started = time.perf_counter()
    phases, last = {}, [started]  # wall clock of each phase, for timing.json

    def phase(name: str) -> None:
        now = time.perf_counter()
        phases[name] = round(now - last[0], 1)
        last[0] = now

    lead = jax.process_index() == 0  # the process that writes files and prints
    write_config = lambda: (out / "config.json").write_text(  # noqa: E731
        json.dumps(dataclasses.asdict(cfg), indent=1)
    )
    if lead and not resume:
        write_config()
    p = build(cfg)
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
        x.shape, x.dtype, sharding=replicated(batch_mesh()), weak_type=x.weak_type
    )
    abstract = jax.tree.map(on_mesh, jax.eval_shape(p.agent.init, key_init))
    rows = []
    step = state = None
    if resume:
        import orbax.checkpoint as ocp

        restore = ocp.args.Composite(state=ocp.args.StandardRestore(abstract))
        step, state, _ = restore_newest(
            out, lambda manager, step: manager.restore(step, args=restore)["state"], log
        )
        if lead:  # a checkpoint reads (or there is none): the run goes on under this config
            write_config()
    ocp, manager = checkpoint_manager(out)
    log_bodies = bodylog.BodyLog(out / "bodies.sqlite", p.space) if lead else None
    greedy_rollout = None if p.agent.scores is None else make_greedy_rollout(p)
    compile_ahead(ahead, p, cfg, step or 0, abstract, greedy_rollout, key_greedy, gif)
    if step is not None:
        ahead.start()
        with open(out / "metrics.csv") as f:
            rows = [r for r in csv.DictReader(f) if int(r["step"]) <= step]
        if lead:
            log_bodies.truncate(step)
        log(f"resumed at step {step}")
    else:
        log("evaluating m0 in every evolution...")
        m0 = p.agent.init.lower(key_init)
        ahead.start()  # after m0's lowering: the two would take turns at the GIL
        state = m0.compile()(key_init)
        step = 0
        first = to_host(state.first)
        if lead:
            log_bodies.truncate(-1)
            log_bodies.add(0, first.morph, first.fitness, first.fitness_std, first.diverged,
                           distance=first.distance, upright=first.upright)
            log_bodies.commit()
    phase("build_and_m0")

    from tensorboardX import SummaryWriter
    from tqdm import tqdm

    writer = SummaryWriter(str(out / "tb")) if lead else None
    bar = tqdm(total=cfg.steps, initial=min(step, cfg.steps), unit="step", dynamic_ncols=True,
               file=sys.stdout, disable=not lead)
    chunks_done, chunk_seconds = 0, []  # (steps, wall clock) of each chunk; the first compiles
    dispatch = None  # seconds until the first chunk call returns (`timing`)
    while step < cfg.steps:
        n = min(cfg.chunk, cfg.steps - step)
        ahead.wait(f"chunk {n}")
        chunk_start = time.perf_counter()
        state, metrics = p.agent.chunk(state, n)
        if dispatch is None:  # when the call returns; to_host then waits for the device
            dispatch = round(time.perf_counter() - chunk_start, 2)
        metrics = to_host(metrics)
        chunk_seconds.append((n, time.perf_counter() - chunk_start))
        bodies = metrics.pop("bodies")
        for i in range(n):
            if lead:
                at = lambda tree, i=i: jax.tree.map(lambda x: x[i], tree)  # noqa: E731
                log_bodies.add(step + i + 1, at(bodies["morph"]), bodies["fitness"][i],
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
            row.update(
                {k: float(v[i]) for k, v in metrics.items() if k not in ("reward", "fitness")}
            )
            rows.append(row)
            for name, value in row.items():
                if lead and name != "step":
                    writer.add_scalar(name.replace("_", "/", 1), value, row["step"])
        step += n
        chunks_done += 1
        bar.update(n)
        bar.set_postfix(reward=f"{row['reward_median']:.3g}", best=f"{row['best_fitness']:.3g}")
        if lead:
            log_bodies.commit()
            with open(out / "metrics.csv", "w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=list(rows[0]))
                w.writeheader()
                w.writerows(rows)
        if chunks_done % cfg.checkpoint_every == 0 or step >= cfg.steps:
            manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state)))
    bar.close()
    manager.wait_until_finished()
    phase("steps")

    # RESULTS
    best, best_fitness, best_params = to_host(
        (state.best_morph, state.best_fitness, state.best_params)
    )
    greedy = None
    if greedy_rollout is not None:  # the baselines have no policy to roll out
        ahead.wait("greedy")
        greedy = greedy_rollout(state.learner, state.first, key_greedy)
    if lead:
        writer.close()
        log_bodies.close()
    barrier("body log written")  # every process reads it in the confirm stage
    phase("greedy_rollout")
    ahead.wait("confirm")
    record, top = confirm_stage(out, p, cfg, step, log)
    phase("confirm")
    ahead.close()  # best.gif's replay and GL
    best, best_fitness, best_params, best_cfg = reported_best(
        out, p, record, top, (best, float(best_fitness), best_params)
    )
    saved = save_controllers(out, p, cfg.seed, best, best_fitness, best_params, greedy, best_cfg)
    phase("controllers")
    if lead:
        if top is not None:  # written last: the stage is done, a --resume keeps it
            record["best_morphology"] = best.to_dict()
            (out / "confirmed.json").write_text(json.dumps(record, indent=1))
        task = p.fitness.task
        write_results(out, p.space, rows, best, best_fitness, greedy, step, saved, gif, record,
                      phase, task.episode_length * task.frame_skip * p.space.template.opt.timestep)
        clock = timing(time.perf_counter() - started, chunk_seconds) | {
            "phases": phases, "first_chunk_dispatch": dispatch}
        (out / "timing.json").write_text(json.dumps(clock, indent=1))
        if clock["step_seconds"]:
            print(f"time: {clock['seconds']:.0f} s, {clock['step_seconds']:.3g} s a step, "
                  f"{clock['outside_steps_seconds']:.0f} s outside the steps (timing.json; "
                  "imports not counted)")


def compile_ahead(ahead: Warmup, p: Pipeline, cfg: RunConfig, start: int, state, greedy_rollout,
                  key_greedy, gif: bool) -> None:
    """The programs a run calls after m0's, given to `ahead` to lower and compile in the order
    they are called: the chunks of the sizes the steps from `start` take,
    `greedy_rollout`'s, the confirm stage's and best.gif's replay (and its GL probes, on a
    thread of their own); `state`: the agent state's shapes and placement."""
    sizes = [min(cfg.chunk, cfg.steps - s) for s in range(start, cfg.steps, cfg.chunk)]
    for n in dict.fromkeys(sizes):
        ahead.compile(f"chunk {n}", lambda n=n: p.agent.chunk.lower(state, n))
    if greedy_rollout is not None:
        ahead.compile("greedy", lambda: greedy_rollout.lower(state.learner, state.first,
                                                             key_greedy))
    confirms = cfg.confirm > 0 and not get_fitness(cfg.fitness).deterministic
    if confirms:
        ahead.compile("confirm", lambda: lower_confirm(p.space, cfg.confirm, p.fitness,
                                                       cfg.confirm_controllers))
    if gif and controllers.has_controllers(p.fitness) and jax.process_index() == 0:
        shown = p.fitness.with_controllers(cfg.confirm_controllers) if confirms else p.fitness
        ahead.compile("replay", lambda: video.lower_replay(p.space, shown))
        ahead.run("gl", video.choose_gl)


def timing(total: float, chunks: list[tuple[int, float]]) -> dict:
    """timing.json: this call's wall clock (a resumed run's since it resumed), split into its
    steps and the rest (building, compiling, m0, the confirm stage, the end phase), from
    `execute`'s start (imports excluded); `execute` adds the seconds of its phases (building and
    m0's evaluation, the steps, the greedy rollout, the confirm stage, saving the controllers,
    the plots and summary, best.gif) and `first_chunk_dispatch`, how long the first chunk call
    takes to return: its host side (compiling or loading, unless the warmup did) where JAX
    dispatches asynchronously, but with MuJoCo Warp on a GPU also most of the step's work, since
    XLA runs Warp's callbacks on the calling thread (docs/benchmarks.md). A step is timed by the
    chunks after the first (whose call may compile); None with one chunk or none."""
    steps = sum(n for n, _ in chunks)
    step = float(np.median([s / n for n, s in chunks[1:]])) if chunks[1:] else None
    return {"seconds": round(total, 1), "steps": steps, "step_seconds": step and round(step, 3),
            "outside_steps_seconds": step and round(total - step * steps, 1)}


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
        if not controllers.has_controllers(p.fitness):
            return morph, record["confirmed"][0]["mean"], None, p.fitness
        kept = controllers.load(out / controllers.DIR / "best")
        return morph, record["confirmed"][0]["mean"], kept.params, kept.fitness
    return (*draw, p.fitness)


def confirm_stage(out: Path, p: Pipeline, cfg: RunConfig, step: int, log=print):
    """The run's confirm stage; every process calls it, after the body log is written.

    The `cfg.confirm` distinct bodies of the highest mean in the body log (`bodylog.
    best_bodies`: ties to the body evaluated more often, then to the one seen first) are each
    evaluated `cfg.confirm_controllers` times from scratch, in one fitness call (`confirm`):
    fresh controllers, no inheritance, keys from `fold_in(PRNGKey(seed), CONFIRM_SALT)`, which
    no other part of the run uses. Skipped, with a note saying why, for a deterministic fitness
    (evaluating again gives the same values) and with --confirm 0; not done again when the run's
    confirmed.json says it was done at this step with these settings (a --resume of a finished
    run).

    Returns:
      (record, top): record is what confirmed.json keeps (env_steps, bodies, controllers,
      "confirmed": summary entries best first, "confirm_note"); top is the best `Confirmed`
      when it was evaluated now, else None.
    """
    n, c = cfg.confirm, cfg.confirm_controllers
    record = {"env_steps": step, "bodies": n, "controllers": c, "confirmed": []}
    done = out / "confirmed.json"
    if done.exists():
        before = json.loads(done.read_text())
        if all(before.get(k) == record[k] for k in ("env_steps", "bodies", "controllers")):
            log("confirm: done when the run finished, kept (confirmed.json)")
            return before, None
    if n == 0:
        record["confirm_note"] = ("not run (--confirm 0): the best body is the highest single "
                                  "draw, a noisy maximum")
        return record, None
    if get_fitness(cfg.fitness).deterministic:
        record["confirm_note"] = (f"not run: the {cfg.fitness} fitness is deterministic, so an "
                                  "evaluation again gives the same values; the best body is the "
                                  "highest single draw")
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


def confirmed_entry(found: Confirmed, logged: dict) -> dict:
    """summary.json's entry of a confirmed body, with its mean and count in the body log."""
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


def walks(entry: dict, seconds: float) -> str:
    """'walks 3.1 m in 5 s, upright 100%' of a confirmed entry ('' without a gait)."""
    if entry.get("distance") is None:
        return ""
    return (f"walks {entry['distance']:.2f} m in {seconds:g} s, upright "
            f"{entry['upright']:.0%} (the whole episode in {entry['upright_whole']:.0%} of "
            "its evaluations)")


def save_controllers(out: Path, p: Pipeline, seed: int, best, best_fitness: float, best_params,
                     greedy: Greedy | None, best_cfg=None) -> list[str]:
    """controllers/best and controllers/stepT for the greedy trajectory's bodies, for a fitness
    that trains controllers; every process calls it. best_cfg: the fitness config the best
    body's controllers were trained under (default the run's; the confirm stage's has C
    controllers). Returns the names saved."""
    if not controllers.has_controllers(p.fitness):
        return []
    bodies = [("best", best, best_params, best_fitness, best_cfg or p.fitness)]
    if greedy is not None:
        bodies += [(f"step{t}", m, params, f, p.fitness) for t, (m, params, f)
                   in enumerate(zip(greedy.morphs, greedy.params, greedy.fitness))]
    for name, morph, params, fitness, fit_cfg in bodies:
        label = name if name == "best" else f"step {name[4:]}"
        saved = controllers.SavedController(p.space, fit_cfg, seed, morph, params, fitness,
                                            label)
        controllers.save(out / controllers.DIR / name, saved)
    return [name for name, *_ in bodies]


def write_results(
    out: Path, space, rows: list[dict], best, best_fitness: float, greedy: Greedy | None,
    steps: int, saved: list[str], gif: bool, record: dict, phase=lambda name: None,
    episode_seconds: float = 5.0,
) -> None:
    """curve.png, best.xml, trajectory.png (if `greedy`), confirmed.png (if the confirm stage's
    `record` confirmed bodies), summary.json and best.gif (if controllers were `saved` and
    `gif`), and a printed digest with the best bodies of the body log and the confirmed ones
    (with their gait: metres in an episode of `episode_seconds`, and upright);
    `phase("results")` is called before best.gif is drawn, `phase("best_gif")` after."""
    col = lambda name: np.array([r[name] for r in rows], float)  # noqa: E731  (resumed: strings)
    plots.plot_curve(
        out / "curve.png", col("step"), col("reward_median"), col("reward_q25"), col("reward_q75")
    )
    (out / "best.xml").write_text(space.to_mjcf(best))
    confirmed = record["confirmed"]
    draw = bodylog.best_draw(out / "bodies.sqlite")
    summary = {
        "best_fitness": best_fitness,  # the confirmed mean; else (not confirmed) the best draw
        "best_morphology": best.to_dict(),
        "best_body": space.canonical(best),
        "best_single_draw": draw,
        "confirmed": confirmed,
        "confirm_note": record["confirm_note"],
        "env_steps": steps,
        "greedy_trajectory": None,
        "best_bodies": bodylog.best_bodies(out / "bodies.sqlite", 10),
        "controllers": saved,
    }
    written = "curve.png best.xml summary.json metrics.csv bodies.sqlite tb/ checkpoints/"
    print_best_bodies(summary["best_bodies"])
    if confirmed:
        print_confirmed(confirmed, record["confirm_note"])
        plots.plot_confirmed(out / "confirmed.png", confirmed)
        written = "confirmed.json confirmed.png " + written
        top = confirmed[0]
        what = (f"confirmed mean {top['mean']:.4g}, 95% CI [{top['ci95'][0]:.4g}, "
                f"{top['ci95'][1]:.4g}] over {top['controllers']} fresh controllers")
        gait = walks(top, episode_seconds)
        if gait:
            print(f"\nconfirmed best {gait}")
    else:
        print(f"\nconfirm: {record['confirm_note']}")
        what = f"fitness {best_fitness:.4g}, its highest single draw"
    print(f"\nhighest single draw: {draw['fitness']:.4g} by {draw['body']} at step "
          f"{draw['step']}")
    print(f"\nbest morphology ({what}):")
    print(space.format(best))
    if greedy is not None:
        morphs, fitness, actions, _ = greedy
        plots.plot_trajectory(out / "trajectory.png", space, morphs, fitness, actions)
        summary["greedy_trajectory"] = [
            {"action": a, "fitness": f, "morphology": m.to_dict()}
            for a, f, m in zip(["m0"] + actions, fitness, morphs)
        ]
        print("\ngreedy trajectory from m0:")
        for a, f in zip(["m0"] + actions, fitness):
            print(f"  {a:<32} fitness {f:.4g}")
        print(f"\nfinal greedy morphology:\n{space.format(morphs[-1])}")
        written = "trajectory.png " + written
    if saved:
        written += " controllers/"
    phase("results")
    if saved and gif:
        shown = video.render(out, "best", mp4=False)
        for note in shown.notes:
            print(f"best.gif: {note}")
        walked = shown.replay.distance[-1]
        written += f" best.gif (drawn by {shown.backend}; the best body walks {walked:.2f} m)"
    elif not saved:
        print("\nno controllers to keep: the fitness trains none (only ppo does), so no best.gif")
    phase("best_gif")
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(f"\nwrote {out}/: {written}")


def print_best_bodies(best: list[dict]) -> None:
    print(f"\nthe {len(best)} distinct bodies of the highest mean fitness in the run "
          "(bodies.sqlite):")
    print(f"  {'mean f':>9} {'evals':>5} {'best f':>9} {'first':>5} {'metres':>6} "
          f"{'upright':>7}  body")
    gait = lambda x, f: "-" if x is None else format(x, f)  # noqa: E731
    for b in best:
        print(f"  {b['mean_fitness']:9.4g} {b['evaluations']:5d} {b['best_fitness']:9.4g} "
              f"{b['first_step']:5d} {gait(b.get('mean_distance'), '.2f'):>6} "
              f"{gait(b.get('mean_upright'), '.0%'):>7}  {b['body']}")


def print_confirmed(confirmed: list[dict], note: str) -> None:
    print(f"\nconfirmed: {note}:")
    print(f"  {'mean':>9} {'95% CI':>21} {'log mean':>9} {'evals':>5} {'metres':>6} "
          f"{'upright':>7} {'whole':>5}  body")
    gait = lambda x, f: "-" if x is None else format(x, f)  # noqa: E731
    for c in confirmed:
        ci = f"[{c['ci95'][0]:.4g}, {c['ci95'][1]:.4g}]"
        print(f"  {c['mean']:9.4g} {ci:>21} {c['log_mean']:9.4g} {c['log_evaluations']:5d} "
              f"{gait(c.get('distance'), '.2f'):>6} {gait(c.get('upright'), '.0%'):>7} "
              f"{gait(c.get('upright_whole'), '.0%'):>5}  {c['body']}")
