"""Re-measure Bad Walker bodies against m* with the PPO fitness, from scratch, over many seeds.

A body is given as the sites of its three feet, long,back,front, each a site name of the space
(back_end, back_inner, front_inner, front_end, middle) or "removed". m* is always added.

  python -m experiments.judge_bad_walker front_inner,back_inner,front_inner \
      middle,front_inner,front_inner \
      --train-steps 50000 --seeds 8
"""

from __future__ import annotations

import argparse
import json

import jax
import numpy as np

import evojax_morph as em
from evojax_morph.spaces import bad_walker as bw


def body(space, spec: str):
    m = space.initial()
    for foot, site in zip((bw.LONG, bw.BACK, bw.FRONT), spec.split(",")):
        if site == "removed":
            m = space.mutate(m, foot, bw.REMOVE)
        elif site != "middle":
            m = space.mutate(m, foot, space.site_names.index(site))
    return m


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("bodies", nargs="+")
    parser.add_argument("--train-steps", type=int, default=50_000)
    parser.add_argument("--seeds", type=int, default=8)
    args = parser.parse_args()
    jax.config.update("jax_default_matmul_precision", "highest")
    space = em.make_space("bad_walker")
    specs = list(dict.fromkeys(args.bodies + ["removed,back_end,front_end"]))  # m* last
    cfg = em.FitnessConfig(ppo=em.standard_ppo(args.train_steps))
    batch = em.stack([body(space, s) for s in specs for _ in range(args.seeds)])
    result = em.evaluate(space, batch, jax.random.PRNGKey(7), cfg)
    fitness = np.asarray(result.fitness).reshape(len(specs), args.seeds)
    star = fitness[-1].mean()
    for spec, f in zip(specs, fitness):
        print(
            json.dumps(
                {
                    "body (long,back,front)": spec,
                    "mean": round(float(f.mean()), 1),
                    "std": round(float(f.std()), 1),
                    "median": round(float(np.median(f)), 1),
                    "at_least_m_star": bool(f.mean() >= star),
                }
            )
        )


if __name__ == "__main__":
    main()
