"""Does a kept controller score alike on MJX's JAX engine and on MuJoCo Warp? Its deterministic
policy (as the PPO fitness scores a trained controller, `ppo.make_evaluate_learners`) run for
--episodes evaluation episodes on each engine from the same reset keys; the engines part after
a few contact steps, so their returns are compared as distributions, not episode by episode.
Appends a line a run to --out.

  python -m experiments.controller_engines   # the Crawler study's best body, CPU: 2 to 3 min
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

import evojax_morph as em
from evojax_morph import ppo
from evojax_morph.physics.engines import get_engine
from evojax_morph.search.confirm import t_interval
from evojax_morph.tasks import Locomotion
from experiments.build_tables import revision

STUDY = Path("docs/figures/crawler_study")


def scores(saved, engine: str, episodes: int, key: jax.Array) -> dict:
    """Controller 0's `episodes` evaluation episodes on `engine`, reset with split(key)."""
    cfg = dataclasses.replace(saved.fitness.ppo, eval_episodes=episodes)
    env = Locomotion(saved.space, saved.fitness.task)
    evaluate = jax.jit(ppo.make_evaluate_learners(saved.space, env, get_engine(engine), cfg))
    first = (lambda x: x[:1]) if saved.fitness.ppo.controllers > 1 else (lambda x: x[None])
    params = jax.tree.map(first, saved.params)
    model = jax.tree.map(lambda x: x[None], saved.space.mjx_model(saved.morph))
    start = time.time()
    with jax.default_matmul_precision("highest"):  # as the fitness trains and scores
        out = jax.device_get(evaluate(key[None], model, params))
    returns = np.asarray(out.returns[0], float)
    return {"engine": engine, "mean": float(returns.mean()), "ci95": list(t_interval(returns)),
            "median": float(np.median(returns)), "returns": returns.round(2).tolist(),
            "distance": float(np.mean(out.distance[0])),
            "whole_episodes": int((out.upright[0] >= 1).sum()),
            "seconds": round(time.time() - start, 1)}  # its compile included


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--controller", type=Path, default=STUDY / "best_controller")
    parser.add_argument("--episodes", type=int, default=32)
    parser.add_argument("--engines", nargs="+", default=["jax", "warp"])
    parser.add_argument("--seed", type=int, default=2026, help="the episodes' reset keys")
    parser.add_argument("--out", type=Path, default=STUDY / "engines.jsonl")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    saved = em.load_controller(args.controller)
    device = jax.devices()[0]
    line = {"controller": str(args.controller), "body": saved.space.canonical(saved.morph),
            "label": saved.label, "value": saved.value, "episodes": args.episodes,
            "seed": args.seed, "device": f"{device.platform}: {device.device_kind}",
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "revision": revision(),
            "engines": [scores(saved, e, args.episodes, jax.random.PRNGKey(args.seed))
                        for e in args.engines]}
    for e in line["engines"]:
        print(f"{e['engine']:>5} on {line['device']}: return {e['mean']:.1f} "
              f"[{e['ci95'][0]:.1f}, {e['ci95'][1]:.1f}] (median {e['median']:.1f}), "
              f"{e['distance']:.2f} m, {e['whole_episodes']} of {args.episodes} episodes whole",
              flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with args.out.open("a") as f:
        f.write(json.dumps(line) + "\n")
    print(f"added a line to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
