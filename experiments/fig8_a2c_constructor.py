"""The source's Figure 8: the actor-critic agent on Constructor with the PPO fitness.

Episode return (f_k - f_0, mean over the parallel evolutions) and the acting policy's entropy,
median over seeds with a .25-.75 band.

  python -m experiments.fig8_a2c_constructor --out docs/figures                 # GPU
  python -m experiments.fig8_a2c_constructor --fitness predefined --steps 16    # CPU smoke
"""

from __future__ import annotations

import argparse

import jax
import matplotlib.pyplot as plt
import numpy as np

from experiments.common import add_setup_flags, band, episode_returns, run_agent, save, setup_from


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_setup_flags(parser, space="constructor", num_envs=16, steps=32, chunk=8, seeds=3)
    args = parser.parse_args()
    jax.config.update("jax_default_matmul_precision", "highest")
    setup = setup_from(args)
    res = run_agent("a2c", setup, args.seeds)
    ret = episode_returns(res["metrics"]["reward"], res["horizon"])
    entropy = res["metrics"]["entropy"]  # (steps, seeds)
    fig, (ax_ret, ax_ent) = plt.subplots(1, 2, figsize=(10, 3.6))
    band(ax_ret, np.arange(1, len(ret) + 1), ret, "a2c")
    band(ax_ent, np.arange(1, len(entropy) + 1), entropy, "a2c")
    ax_ret.set(
        title=f"A2C, Constructor, {args.fitness} fitness", xlabel="episode", ylabel="episode return"
    )
    ax_ent.set(
        title="policy entropy (nats, valid actions)", xlabel="environment step", ylabel="entropy"
    )
    summary = {
        "returns": ret.tolist(),
        "entropy": entropy.tolist(),
        "best_fitness": res["metrics"]["best_fitness"].tolist(),
        "step_seconds": float(np.median(res["step_seconds"])),
    }
    save(fig, args.out or "runs/figures", "fig8_a2c_constructor", summary)


if __name__ == "__main__":
    main()
