"""Do the RL agents find better bodies than evolution at the same number of fitness evaluations?

Double-DQN, actor-critic, NGE-like evolution and random mutation walks, each --seeds runs of
--num-envs parallel evolutions (every method evaluates num_envs bodies per step, so equal steps
mean equal evaluations). Plots the best fitness found against evaluations and against
wall-clock time (compilation excluded; the seeds of a method run together in one batch), median
over seeds with a .25-.75 band. With --landscape (from landscapes.py) each run's best body is
also re-scored by its landscape mean, measured from scratch at a long budget, with its rank and
regret: the in-run fitness is one noisy evaluation with an inherited controller.

  python experiments/compare.py --landscape docs/landscapes/landscape_bad_walker.json --out docs/figures   # GPU
  python experiments/compare.py --fitness predefined --steps 8        # CPU smoke
"""

from __future__ import annotations

import argparse

import jax
import matplotlib.pyplot as plt
import numpy as np
from common import add_setup_flags, band, run_agent, save, setup_from

from evojax_morph import landscape

METHODS = ("ddqn", "a2c", "evolution", "random")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_setup_flags(parser, space="bad_walker", num_envs=16, steps=12, chunk=4, seeds=5)
    parser.add_argument("--landscape", default=None, help="a landscape_SPACE.json to rank the best bodies in")
    args = parser.parse_args()
    jax.config.update("jax_default_matmul_precision", "highest")
    setup = setup_from(args)
    ls = landscape.Landscape.load(args.landscape) if args.landscape else None
    fig, (ax_evals, ax_wall) = plt.subplots(1, 2, figsize=(10, 3.6))
    summary, finals = {"setup": setup.__dict__, "seeds": args.seeds}, {}
    for method in METHODS:
        res = run_agent(method, setup, args.seeds)
        best = res["metrics"]["best_fitness"]  # (steps, seeds)
        evals = setup.num_envs * np.arange(1, len(best) + 1)
        wall = np.cumsum(res["step_seconds"])
        band(ax_evals, evals, best, method)
        band(ax_wall, wall, best, method)
        row = {"best_fitness": best[-1].tolist(), "median_best_fitness": float(np.median(best[-1])),
               "seconds_per_step": float(np.median(res["step_seconds"])),
               "best_bodies": [res["space"].format(b) for b in res["best_bodies"]]}
        if ls is not None:
            row["landscape_mean"] = [float(ls.mean[ls.index(b)]) for b in res["best_bodies"]]
            row["rank"] = [ls.rank(b) for b in res["best_bodies"]]
            row["regret"] = [ls.regret(b) for b in res["best_bodies"]]
        summary[method], finals[method] = row, np.asarray(row.get("landscape_mean", row["best_fitness"]))
        print(method, {k: v for k, v in row.items() if k != "best_bodies"}, flush=True)
    # Probability that a seed of the agent beats a seed of evolution (ties count half).
    for agent in ("ddqn", "a2c"):
        a, e = finals[agent][:, None], finals["evolution"][None, :]
        summary[f"{agent}_beats_evolution"] = float(np.mean((a > e) + 0.5 * (a == e)))
        print(f"P({agent} > evolution) = {summary[f'{agent}_beats_evolution']:.2f}")
    ax_evals.set(title=f"{setup.space}, {setup.fitness} fitness", xlabel="fitness evaluations per run",
                 ylabel="best fitness found")
    ax_wall.set(title="against wall-clock (all seeds at once)", xlabel="seconds", ylabel="best fitness found")
    ax_evals.legend()
    save(fig, args.out or "runs/figures", f"compare_{setup.space}", summary)


if __name__ == "__main__":
    main()
