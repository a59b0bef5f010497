"""What a run's report says (its stage: `stages.Report`): summary.json and its printed digest,
the plots and best.gif handed to the recorder, timing.json, from the earlier stages' results
(`stages.Evolved`, `stages.Best`)."""

from __future__ import annotations

import jax
import numpy as np

from evojax_morph.search.pipeline import Greedy
from evojax_morph.tasks import gait_word


def timing(total: float, chunks: list[tuple[int, float]]) -> dict:
    """timing.json: this call's wall clock (a resumed run's since it resumed), split into its
    steps and the rest (building, compiling, m0, the confirm stage, the end phase), from
    `driver.execute`'s start (imports excluded); it adds the seconds of its phases (building and
    m0's evaluation, the steps, the greedy walk, the confirm stage with the greedy trajectory's
    evaluation, saving the controllers,
    the plots and summary, best.gif) and `first_chunk_dispatch`, how long the first chunk call
    takes to return: its host side (compiling or loading, unless the warmup did) where JAX
    dispatches asynchronously, but with MuJoCo Warp on a GPU also most of the step's work, since
    XLA runs Warp's callbacks on the calling thread (docs/benchmarks.md). Finer, to say where a
    phase goes: `chunk_seconds` (each chunk call and its host copy), `parts` (the build, and m0's
    lowering, compiling or loading, the wait for the engine's preload with MuJoCo Warp, and
    evaluation) and `waits` (how long the main thread waited for each compile-ahead job,
    compiling it there with Warp on a GPU; and, as "preload", for the engine's preload before a
    resumed run's first chunk). A step is timed by the chunks after the first (whose call may
    compile); None with one chunk or none."""
    steps = sum(n for n, _ in chunks)
    step = float(np.median([s / n for n, s in chunks[1:]])) if chunks[1:] else None
    return {"seconds": round(total, 1), "steps": steps, "step_seconds": step and round(step, 3),
            "outside_steps_seconds": step and round(total - step * steps, 1)}


def where(cfg) -> dict:
    """What timing.json's seconds ran on: the devices (the fitness batch splits across all of
    them, `sharding`), the engine, the batch and jax's version."""
    device = jax.devices()[0]
    return {"devices": jax.device_count(), "processes": jax.process_count(),
            "device": f"{device.platform}: {device.device_kind}", "physics": cfg.physics,
            "num_envs": cfg.num_envs, "controllers": cfg.controllers, "jax": jax.__version__}


def walks(entry: dict, seconds: float) -> str:
    """'walks 3.1 m in 5 s, upright 100% ...' of a confirmed entry, "moves" where it does not
    walk by `tasks.gait_word` ('' without a gait)."""
    if entry.get("distance") is None:
        return ""
    word = gait_word(entry["distance"], entry["upright_whole"])
    return (f"{word} {entry['distance']:.2f} m in {seconds:g} s, upright "
            f"{entry['upright']:.0%} (the whole episode in {entry['upright_whole']:.0%} of "
            "its evaluations)")


def write_results(run, evolved, best, record, phase=lambda name: None) -> None:
    """summary.json and a printed digest of it, with the best bodies of the body log and the
    confirmed ones (with their gait: metres in an episode, and upright); curve.png, best.xml,
    trajectory.png (if the confirm stage evaluated a greedy trajectory), confirmed.png (if the
    confirm stage's record confirmed bodies) and best.gif (if `run.gif`), by the `record`er.
    `phase("results")` is called before best.gif is drawn, `phase("best_gif")` after."""
    space, greedy, saved = run.p.space, best.greedy, best.saved
    task = run.p.fitness.task
    episode_seconds = task.episode_length * task.frame_skip * space.template.opt.timestep
    k = None if greedy is None else greedy.controllers or run.p.fitness.ppo.controllers
    summary = {
        "best_fitness": best.fitness,  # the confirmed mean; else (not confirmed) the best draw
        "best_morphology": best.morph.to_dict(),
        "best_body": space.canonical(best.morph),
        "best_single_draw": evolved.best_draw,
        "confirmed": best.record["confirmed"],
        "confirm_note": best.record["confirm_note"],
        "env_steps": evolved.step,
        "greedy_trajectory": None if greedy is None else [
            {"action": a, "fitness": f, "morphology": m.to_dict(), "controllers": k}
            for a, f, m in zip(["m0"] + greedy.actions, greedy.fitness, greedy.morphs)],
        "best_bodies": evolved.best_bodies,
        "controllers": list(saved),
    }
    print_summary(summary, space, best.morph, greedy, episode_seconds)
    written = " ".join(record.figures(summary, best.morph, greedy) + [
        "curve.png best.xml summary.json metrics.csv bodies.sqlite tb/ checkpoints/"])
    written += " controllers/" if saved else ""
    phase("results")  # before best.gif, drawn last: a failing OpenGL leaves the rest written
    if run.gif:
        shown = record.video(saved["best"])
        for note in shown.notes:
            print(f"best.gif: {note}")
        moved = shown.replay.distance[-1]
        which = ("its best confirming controller (the confirmed gait above is the mean over "
                 "all of them)" if summary["confirmed"] else "its first controller")
        written += f" best.gif (drawn by {shown.backend}: {which}, {moved:.2f} m in its episode)"
    elif not saved:
        print("\nno controllers to keep: the fitness trains none (only ppo does), so no best.gif")
    phase("best_gif")
    record.summary(summary)
    print(f"\nwrote {run.out}/: {written}")


def print_summary(summary: dict, space, best, greedy: Greedy | None,
                  episode_seconds: float) -> None:
    """The digest of a run's `summary`: the best bodies of its log, the confirmed ones, its
    highest single draw, its best body and its greedy trajectory."""
    print_best_bodies(summary["best_bodies"])
    confirmed, draw = summary["confirmed"], summary["best_single_draw"]
    if confirmed:
        print_confirmed(confirmed, summary["confirm_note"])
        top = confirmed[0]
        what = (f"confirmed mean {top['mean']:.4g}, 95% CI [{top['ci95'][0]:.4g}, "
                f"{top['ci95'][1]:.4g}] over {top['controllers']} fresh controllers")
        gait = walks(top, episode_seconds)
        if gait:
            print(f"\nconfirmed best {gait}")
    else:
        print(f"\nconfirm: {summary['confirm_note']}")
        what = f"fitness {summary['best_fitness']:.4g}, its highest single draw"
    print(f"\nhighest single draw: {draw['fitness']:.4g} by {draw['body']} at step "
          f"{draw['step']}")
    print(f"\nbest morphology ({what}):")
    print(space.format(best))
    if greedy is not None:
        k = summary["greedy_trajectory"][0]["controllers"]
        print(f"\ngreedy trajectory from m0 ({greedy_header(greedy.confirmed, k)}):")
        for a, f in zip(["m0"] + greedy.actions, greedy.fitness):
            print(f"  {a:<32} fitness {f:.4g}")
        print(f"\nfinal greedy morphology:\n{space.format(greedy.morphs[-1])}")


def greedy_header(confirmed: bool, k: int) -> str:
    """How the greedy trajectory's fitness was measured, `k` fresh controllers a body, in the
    confirm stage's call if `confirmed`: the printed digest's words."""
    if confirmed:
        return f"each body the mean of {k} fresh controllers, in the confirm stage's call"
    return ("each body with a fresh controller" if k == 1 else
            f"each body with {k} fresh controllers, their mean")


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
