"""The host side of a run: the outer Python loop over jitted chunks, with its files.

`execute(cfg, out, resume)` runs `pipeline.build(cfg)` chunk by chunk and writes the run
directory: config.json, metrics.csv, TensorBoard events (tb/), curve.png, trajectory.png,
best.xml, summary.json and Orbax checkpoints, from which `resume` continues.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import sys
from pathlib import Path

import jax
import numpy as np

from evojax_morph import plots
from evojax_morph.pipeline import RunConfig, build, make_greedy_rollout
from evojax_morph.sharding import batch_mesh, replicated, to_host


def checkpoint_manager(out: Path):
    import orbax.checkpoint as ocp

    options = ocp.CheckpointManagerOptions(max_to_keep=2, create=True)
    return ocp, ocp.CheckpointManager(out.resolve() / "checkpoints", options=options)


def fresh_run_dir(cfg: RunConfig) -> Path:
    """runs/SPACE-FITNESS-seedS, or the first of -2, -3, ... that does not exist yet."""
    base = Path("runs") / f"{cfg.space}-{cfg.fitness}-seed{cfg.seed}"
    out, n = base, 1
    while out.exists():
        n += 1
        out = base.with_name(f"{base.name}-{n}")
    return out


def execute(cfg: RunConfig, out: Path, resume: bool) -> None:
    """Runs `cfg` in the directory `out` (checked writable), from its last checkpoint if
    `resume`; every process calls it, process 0 writes the files and prints."""
    lead = jax.process_index() == 0  # the process that writes files and prints
    if lead:
        (out / "config.json").write_text(json.dumps(dataclasses.asdict(cfg), indent=1))
    p = build(cfg)
    ocp, manager = checkpoint_manager(out)
    log = print if lead else (lambda *a, **k: None)
    log(f"evojax_morph: {cfg.agent} on {cfg.space} with {cfg.fitness} fitness, {cfg.num_envs} "
        f"parallel evolutions x {cfg.steps} steps, horizon {p.env.horizon}, on "
        f"{jax.device_count()} {jax.default_backend()} device(s) in {jax.process_count()} "
        f"process(es); run in {out}")

    key = jax.random.PRNGKey(cfg.seed)
    key_init, key_greedy = jax.random.split(key)
    rows = []
    if resume and manager.latest_step() is not None:
        step = manager.latest_step()
        # Restored onto this run's devices, however many the saving run had.
        on_mesh = lambda x: jax.ShapeDtypeStruct(  # noqa: E731
            x.shape, x.dtype, sharding=replicated(batch_mesh())
        )
        abstract = jax.tree.map(on_mesh, jax.eval_shape(p.agent.init, key_init))
        restore = ocp.args.Composite(state=ocp.args.StandardRestore(abstract))
        state = manager.restore(step, args=restore)["state"]
        with open(out / "metrics.csv") as f:
            rows = [r for r in csv.DictReader(f) if int(r["step"]) <= step]
        log(f"resumed at step {step}")
    else:
        log("evaluating m0 in every evolution...")
        state = p.agent.init(key_init)
        step = 0

    from tensorboardX import SummaryWriter
    from tqdm import tqdm

    writer = SummaryWriter(str(out / "tb")) if lead else None
    bar = tqdm(total=cfg.steps, initial=min(step, cfg.steps), unit="step", dynamic_ncols=True,
               file=sys.stdout, disable=not lead)
    chunks_done = 0
    while step < cfg.steps:
        n = min(cfg.chunk, cfg.steps - step)
        state, metrics = p.agent.chunk(state, n)
        metrics = to_host(metrics)
        for i in range(n):
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
            with open(out / "metrics.csv", "w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=list(rows[0]))
                w.writeheader()
                w.writerows(rows)
        if chunks_done % cfg.checkpoint_every == 0 or step >= cfg.steps:
            manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state)))
    bar.close()
    manager.wait_until_finished()

    # RESULTS
    best, best_fitness = to_host((state.best_morph, state.best_fitness))
    greedy = None
    if p.agent.scores is not None:  # the baselines have no policy to roll out
        greedy = make_greedy_rollout(p)(state.learner, state.first, key_greedy)
    if lead:
        writer.close()
        write_results(out, p.space, rows, best, float(best_fitness), greedy, step)


def write_results(
    out: Path, space, rows: list[dict], best, best_fitness: float, greedy, steps: int
) -> None:
    """curve.png, best.xml, trajectory.png (if `greedy`) and summary.json, and a printed digest."""
    col = lambda name: np.array([r[name] for r in rows], float)  # noqa: E731  (resumed: strings)
    plots.plot_curve(
        out / "curve.png", col("step"), col("reward_median"), col("reward_q25"), col("reward_q75")
    )
    (out / "best.xml").write_text(space.to_mjcf(best))
    summary = {
        "best_fitness": best_fitness,
        "best_morphology": best.to_dict(),
        "env_steps": steps,
        "greedy_trajectory": None,
    }
    print(f"\nbest morphology (fitness {best_fitness:.4g}):")
    print(space.format(best))
    written = "curve.png best.xml summary.json metrics.csv tb/ checkpoints/"
    if greedy is not None:
        morphs, fitness, actions = greedy
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
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(f"\nwrote {out}/: {written}")
