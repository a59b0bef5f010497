"""Do the RL agents find better bodies than evolution at the same number of fitness evaluations?

Double-DQN, actor-critic, NGE-like evolution and random mutation walks, each --seeds runs of
--num-envs parallel evolutions (every method evaluates num_envs bodies per step, so equal steps
mean equal evaluations). Plots the best fitness found against evaluations and against
wall-clock time (compilation excluded; the seeds of a method run together in one batch), median
over seeds with a .25-.75 band. With --landscape (from landscapes.py) each run's best body is
also re-scored by its landscape mean, measured from scratch at a long budget, with its rank and
regret: the in-run fitness is one noisy evaluation with an inherited controller.

The summary JSON is written after every method; run again with the same flags and --out to
resume: methods already in it (same settings) are kept, not rerun.

  python -m experiments.compare --landscape docs/landscapes/landscape_bad_walker.json \
    --out docs/figures                                                # GPU
  python -m experiments.compare --fitness predefined --steps 8        # CPU smoke
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import matplotlib.pyplot as plt
import numpy as np

from evojax_morph import landscape
from experiments.common import add_setup_flags, band, run_agent, save, setup_from

METHODS = ("ddqn", "a2c", "evolution", "random")


def run_method(method, setup, seeds, ls) -> dict:
    res = run_agent(method, setup, seeds)
    best = res["metrics"]["best_fitness"]  # (steps, seeds)
    row = {
        "curve": best.tolist(),
        "step_seconds": res["step_seconds"].tolist(),
        "best_fitness": best[-1].tolist(),
        "median_best_fitness": float(np.median(best[-1])),
        "seconds_per_step": float(np.median(res["step_seconds"])),
        "best_bodies": [res["space"].format(b) for b in res["best_bodies"]],
    }
    if ls is not None:
        row["landscape_mean"] = [float(ls.mean[ls.index(b)]) for b in res["best_bodies"]]
        row["rank"] = [ls.rank(b) for b in res["best_bodies"]]
        row["regret"] = [ls.regret(b) for b in res["best_bodies"]]
    return row


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_setup_flags(parser, space="bad_walker", num_envs=16, steps=12, chunk=4, seeds=5)
    parser.add_argument(
        "--landscape", default=None, help="a landscape_SPACE.json to rank the best bodies in"
    )
    parser.add_argument(
        "--methods",
        default=",".join(METHODS),
        help="comma-separated subset of " + ",".join(METHODS),
    )
    args = parser.parse_args()
    jax.config.update("jax_default_matmul_precision", "highest")
    setup = setup_from(args)
    out = Path(args.out or "runs/figures")
    name = f"compare_{setup.space}"
    ls = landscape.Landscape.load(args.landscape) if args.landscape else None
    summary = {"setup": setup.__dict__, "seeds": args.seeds, "landscape": args.landscape}
    previous = out / f"{name}.json"
    if previous.exists():
        old = json.loads(previous.read_text())
        if all(old.get(k) == summary[k] for k in summary):
            summary = old
            print("resuming: kept", [m for m in METHODS if m in old], flush=True)
    for method in args.methods.split(","):
        if method not in METHODS:
            raise SystemExit(f"unknown method {method!r}; choose from {METHODS}")
        if method in summary:
            continue
        summary[method] = run_method(method, setup, args.seeds, ls)
        print(
            method,
            {
                k: v
                for k, v in summary[method].items()
                if k not in ("best_bodies", "curve", "step_seconds")
            },
            flush=True,
        )
        out.mkdir(parents=True, exist_ok=True)
        previous.write_text(json.dumps(summary, indent=1))

    fig, (ax_evals, ax_wall) = plt.subplots(1, 2, figsize=(10, 3.6))
    done = [m for m in METHODS if m in summary]
    for method in done:
        best = np.asarray(summary[method]["curve"])
        band(ax_evals, setup.num_envs * np.arange(1, len(best) + 1), best, method)
        band(ax_wall, np.cumsum(summary[method]["step_seconds"]), best, method)
    # Probability that a seed of the agent beats a seed of evolution (ties count half), scored by
    # the landscape mean of its best body when there is a landscape.
    score = "landscape_mean" if ls is not None else "best_fitness"
    for agent in ("ddqn", "a2c", "random"):
        if agent in summary and "evolution" in summary:
            a, e = (
                np.asarray(summary[agent][score])[:, None],
                np.asarray(summary["evolution"][score])[None, :],
            )
            summary[f"{agent}_beats_evolution"] = float(np.mean((a > e) + 0.5 * (a == e)))
            print(f"P({agent} > evolution) = {summary[f'{agent}_beats_evolution']:.2f}")
    ax_evals.set(
        title=f"{setup.space}, {setup.fitness} fitness",
        xlabel="fitness evaluations per run",
        ylabel="best fitness found (in run)",
    )
    ax_wall.set(
        title="against wall-clock (all seeds at once)",
        xlabel="seconds",
        ylabel="best fitness found",
    )
    ax_evals.legend()
    save(fig, out, name, summary)


if __name__ == "__main__":
    main()
