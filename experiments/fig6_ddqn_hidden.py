"""The source's Figure 6: Double-DQN on Bad Walker with the PPO fitness, GNN width 20 and 100.

Episode return (f_k - f_0, mean over the parallel evolutions) against episodes and the best
fitness found, median over seeds with a .25-.75 band.

  python -m experiments.fig6_ddqn_hidden --out docs/figures                 # GPU
  python -m experiments.fig6_ddqn_hidden --fitness predefined --steps 8     # CPU smoke
"""

from __future__ import annotations

import argparse
import dataclasses

import jax
import matplotlib.pyplot as plt
import numpy as np

from experiments.common import add_setup_flags, band, episode_returns, run_agent, save, setup_from


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_setup_flags(parser, space="bad_walker", num_envs=16, steps=16, chunk=4, seeds=3)
    args = parser.parse_args()
    jax.config.update("jax_default_matmul_precision", "highest")
    fig, (ax_ret, ax_best) = plt.subplots(1, 2, figsize=(10, 3.6))
    summary = {}
    for hidden in (20, 100):
        setup = dataclasses.replace(setup_from(args), hidden=hidden)
        res = run_agent("ddqn", setup, args.seeds)
        ret = episode_returns(res["metrics"]["reward"], res["horizon"])
        band(ax_ret, np.arange(1, len(ret) + 1), ret, f"hidden {hidden}")
        best = res["metrics"]["best_fitness"]  # (steps, seeds)
        band(ax_best, np.arange(1, len(best) + 1), best, f"hidden {hidden}")
        summary[f"hidden_{hidden}"] = {
            "returns": ret.tolist(),
            "best_fitness": best.tolist(),
            "step_seconds": float(np.median(res["step_seconds"])),
        }
    ax_ret.set(
        title=f"DDQN, Bad Walker, {args.fitness} fitness", xlabel="episode", ylabel="episode return"
    )
    ax_best.set(title="best fitness found", xlabel="environment step", ylabel="fitness")
    ax_ret.legend()
    save(fig, args.out or "runs/figures", "fig6_ddqn_hidden", summary)


if __name__ == "__main__":
    main()
