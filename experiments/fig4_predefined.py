"""The source's Figure 4: both agents on both spaces with the predefined (hand-crafted) fitness.

Episode return (f_k - f_0 over an episode of mutations, mean over the parallel evolutions)
against episodes, median over seeds with a .25-.75 band; the dashed line is Bad Walker's
best return possible from m0 (the optimum's fitness minus m0's, found by enumeration).
Cheap: runs on CPU.

  python -m experiments.fig4_predefined --out docs/figures
"""

from __future__ import annotations

import argparse
import dataclasses

import matplotlib.pyplot as plt
import numpy as np

from experiments.common import add_setup_flags, band, episode_returns, run_agent, save, setup_from


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_setup_flags(
        parser, fitness="predefined", num_envs=16, steps=400, chunk=100, hidden=64, seeds=5
    )
    args = parser.parse_args()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    summary = {}
    for ax, space_name in zip(axes, ("bad_walker", "constructor")):
        setup = dataclasses.replace(setup_from(args), space=space_name, fitness="predefined")
        for agent in ("ddqn", "a2c"):
            res = run_agent(agent, setup, args.seeds)
            space = res["space"]
            ret = episode_returns(res["metrics"]["reward"], res["horizon"])
            band(ax, np.arange(1, len(ret) + 1), ret, agent)
            summary[f"{space_name}/{agent}"] = {
                "final_return_median": float(np.median(ret[-5:].mean(0))),
                "returns": ret.tolist(),
            }
        if space_name == "bad_walker":  # small enough to enumerate (Constructor is not, at depth 8)
            bodies, _ = space.enumerate_bodies()
            fits = np.array([float(space.predefined_fitness(b)) for b in bodies])
            best = fits.max() - float(space.predefined_fitness(space.initial()))
            summary[f"{space_name}/best_possible_return"] = best
            ax.axhline(best, ls="--", color="k", lw=1, label="best possible")
        ax.set(
            title=f"{space_name}, predefined fitness",
            xlabel="episode",
            ylabel="episode return f_k - f_0",
        )
        ax.legend()
    save(fig, args.out or "runs/figures", "fig4_predefined", summary)


if __name__ == "__main__":
    main()
