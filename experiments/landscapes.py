"""Exhaustive PPO-fitness landscapes: every body reachable in Bad Walker, and in Constructor up
to --constructor-depth mutations from m0, each trained from scratch with --seeds keys.

Writes landscape_SPACE.json (em.landscape.Landscape: canonical names, bodies, depth, mean and
std of fitness) and landscape_SPACE.png (bodies sorted by mean fitness, with std bars).

  python -m experiments.landscapes --out docs/landscapes                        # GPU
  python -m experiments.landscapes --spaces bad_walker --train-steps 640 --seeds 1   # CPU smoke
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import evojax_morph as em  # noqa: E402
from evojax_morph import landscape  # noqa: E402


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--spaces", nargs="+", default=["bad_walker", "constructor"])
    parser.add_argument(
        "--train-steps", type=int, default=50_000, help="PPO steps per evaluation (Bad Walker)"
    )
    parser.add_argument("--constructor-train-steps", type=int, default=20_000)
    parser.add_argument("--constructor-depth", type=int, default=3)
    parser.add_argument("--seeds", type=int, default=4, help="evaluations per body (Bad Walker)")
    parser.add_argument("--constructor-seeds", type=int, default=2)
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--out", default="runs/landscapes")
    args = parser.parse_args()
    jax.config.update("jax_default_matmul_precision", "highest")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name in args.spaces:
        con = name == "constructor"
        steps = args.constructor_train_steps if con else args.train_steps
        cfg = em.FitnessConfig(ppo=em.standard_ppo(steps))
        start = time.perf_counter()
        ls = landscape.measure(
            em.make_space(name),
            cfg,
            args.constructor_seeds if con else args.seeds,
            jax.random.PRNGKey(0),
            args.constructor_depth if con else None,
            args.batch,
        )
        ls.config["seconds_with_compile"] = time.perf_counter() - start
        ls.config["device"] = jax.devices()[0].device_kind
        ls.save(out / f"landscape_{name}.json")
        order = np.argsort(-ls.mean)
        fig, ax = plt.subplots(figsize=(10, 3.2))
        ax.errorbar(
            np.arange(len(order)), ls.mean[order], yerr=ls.std[order], fmt=".", ms=3, lw=0.6
        )
        ax.set(
            title=f"{name}: {len(order)} bodies, PPO fitness at {steps} steps, {ls.seeds} seeds",
            xlabel="bodies, best first",
            ylabel="fitness (mean, std)",
        )
        fig.tight_layout()
        fig.savefig(out / f"landscape_{name}.png", dpi=120)
        space = em.make_space(name)
        m0 = ls.index(space.initial())
        print(
            f"{name}: {len(order)} bodies in {ls.config['seconds_with_compile']:.0f} s; "
            f"best {ls.mean.max():.1f} "
            f"({ls.keys[order[0]]}); m0 {ls.mean[m0]:.1f} rank {ls.rank(space.initial())}",
            flush=True,
        )
        if not con:
            opt = space.optimum()
            print(
                f"  m* {ls.mean[ls.index(opt)]:.1f} +- {ls.std[ls.index(opt)]:.1f}, "
                f"rank {ls.rank(opt)}, "
                f"regret {ls.regret(opt):.1f}"
            )
        for i in order[:5]:
            print(f"  {ls.mean[i]:8.1f} +- {ls.std[i]:6.1f}  depth {ls.depths[i]}  {ls.keys[i]}")


if __name__ == "__main__":
    main()
