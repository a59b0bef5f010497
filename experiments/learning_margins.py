"""The statistics the learning tests assert, over many seeds: where to put their thresholds.

tests/test_fitness.py (PPO) and tests/test_search.py (actor-critic) assert medians over 12
seeds at a small CPU budget. This script measures the per-seed values over --seeds seeds (same
bodies and budget as the tests, other keys) and the spread of a 12-seed median (bootstrap), so
each threshold can sit well below what is observed.

--measure ppo (tests/test_fitness.py):

  m*          learned fitness of m* minus its zero-controller fitness (the same keys)
  inherit0    child fitness with its parent's controller, untrained, minus with a fresh one
  inherit     child trained from the parent's controller minus from scratch, same budget

--measure a2c (tests/test_search.py, the tests' own functions on seeds --offset ...):

  constructor/final Constructor: mean episode return of the last 5 of 25 episodes (best 800)
  constructor/rise  Constructor: that minus the return of the first episode
  constructor/fall  Constructor: the policy's entropy over the first 8 steps minus the last 8
  bad_walker/final  Bad Walker: mean episode return of the last 5 of 80 episodes (best 1.33)

Run it under other CPUs' rounding too: XLA_FLAGS=--xla_cpu_max_isa=AVX2 (or AVX).

  python -m experiments.learning_margins --seeds 30
  python -m experiments.learning_margins --measure a2c --seeds 24
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import evojax_morph as em
from evojax_morph import ppo
from evojax_morph.spaces import bad_walker as bw


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--measure", choices=("ppo", "a2c"), default="ppo")
    parser.add_argument("--seeds", type=int, default=30)
    parser.add_argument("--train-steps", type=int, default=40_000)
    parser.add_argument("--subset", type=int, default=12, help="seeds per test statistic")
    parser.add_argument("--offset", type=int, default=100, help="key offset (the tests use 0)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    if args.measure == "a2c":
        report = measure_a2c(args)
    else:
        report = measure_ppo(args)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(report, f, indent=1)


def summarise(report: dict, values: dict, subset: int) -> None:
    """Adds each statistic's values, median and 12-seed-median quantiles to `report`; prints."""
    rng = np.random.default_rng(0)
    for name, v in values.items():
        medians = np.median(rng.choice(v, (2000, subset)), 1)
        report[name] = {
            "values": v.round(3).tolist(),
            "median": float(np.median(v)),
            "median_of_subset_p01": float(np.quantile(medians, 0.01)),
            "median_of_subset_p05": float(np.quantile(medians, 0.05)),
        }
        print(
            f"{name:>9}: median {np.median(v):8.2f}, {subset}-seed median 1% / 5% quantile "
            f"{report[name]['median_of_subset_p01']:8.2f} / "
            f"{report[name]['median_of_subset_p05']:8.2f}; "
            f"values {[round(float(x), 2) for x in np.sort(v)]}",
            flush=True,
        )


def measure_a2c(args) -> dict:
    """The actor-critic's learning statistics, by the learning tests' own functions."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_search import a2c_bad_walker, a2c_learning

    seeds = range(args.offset, args.offset + args.seeds)
    start = time.perf_counter()
    returns, fall = a2c_learning(seeds)
    final = returns[:, -5:].mean(1)
    walker = a2c_bad_walker(seeds)
    report = {
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "seeds": [seeds.start, seeds.stop - 1],
        "constructor/returns": returns.round(1).tolist(),
        "seconds": round(time.perf_counter() - start, 1),
    }
    values = {
        "constructor/final": final,
        "constructor/rise": final - returns[:, 0],
        "constructor/fall": fall,
        "bad_walker/final": walker,
    }
    summarise(report, values, args.subset)
    return report


def measure_ppo(args) -> dict:
    """The PPO fitness's learning and inheritance statistics (tests/test_fitness.py)."""
    walker = em.make_space("bad_walker")
    cfg = em.standard_ppo(args.train_steps)
    n = args.seeds
    init, train = ppo.make_train(walker, em.TaskConfig(), cfg)
    train = jax.jit(train)
    _, evaluate = ppo.make_train(walker, em.TaskConfig(), em.standard_ppo(0))
    evaluate = jax.jit(evaluate)
    child = walker.mutate(walker.optimum(), bw.FRONT, 2)  # front foot one site inward
    keys = jax.random.split(jax.random.PRNGKey(args.offset), 2 * n)
    fresh = jax.jit(jax.vmap(init))(keys)
    zero = lambda p: p._replace(policy=jax.tree.map(jnp.zeros_like, p.policy))
    half = lambda tree, i: jax.tree.map(lambda x: x[i * n : (i + 1) * n], tree)

    stars, children = em.stack([walker.optimum()] * n), em.stack([child] * n)
    out1 = train(keys[:n], stars, half(fresh, 0))
    parents = out1.params
    zero_fit = evaluate(keys[:n], stars, zero(half(fresh, 0))).fitness
    inherited0 = evaluate(keys[n:], children, parents).fitness
    fresh0 = evaluate(keys[n:], children, half(fresh, 1)).fitness
    inherited = train(keys[n:], children, parents).fitness
    scratch = train(keys[n:], children, half(fresh, 1)).fitness
    values = {
        "m*": np.asarray(out1.fitness - zero_fit),
        "inherit0": np.asarray(inherited0 - fresh0),
        "inherit": np.asarray(inherited - scratch),
    }
    report = {
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "seeds": n,
        "train_steps": args.train_steps,
        "m*_learned": np.asarray(out1.fitness).round(1).tolist(),
        "zero": np.asarray(zero_fit).round(2).tolist(),
    }
    summarise(report, values, args.subset)
    return report


if __name__ == "__main__":
    main()
