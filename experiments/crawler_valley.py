"""Can a search that keeps only children better than their parents leave the Crawler's torso?
m0 (the torso alone) and every body one mutation from it, each confirmed by --controllers
controllers trained from scratch (`em.confirm`, the walking task, the study's PPO budget).

  python -m experiments.crawler_valley --out docs/figures   # CPU: about 36 min on 2 cores
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

import evojax_morph as em
from evojax_morph.search.pipeline import build
from experiments.build_tables import revision
from experiments.common import Setup, run_config


def neighbourhood(space) -> dict:
    """{canonical body: (its name, Morphology)}: m0 first, then every distinct body one valid
    mutation from it, in the order of `action_mask`."""
    m0 = space.initial()
    found = {space.canonical(m0): ("m0", m0)}
    for node, mutation in zip(*np.nonzero(np.asarray(space.action_mask(m0))), strict=True):
        child = space.mutate(m0, int(node), int(mutation))
        found.setdefault(space.canonical(child),
                         (f"{space.mutation_names[mutation]} on node {node}", child))
    return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--controllers", type=int, default=4)
    parser.add_argument("--train-steps", type=int, default=50_000)
    parser.add_argument("--physics", default="jax")
    parser.add_argument("--out", type=Path, default=Path("docs/figures"))
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    space = em.make_space("crawler")
    setup = Setup(space="crawler", fitness="ppo", task="walk", train_steps=args.train_steps,
                  num_envs=64, steps=32, chunk=2, hidden=64, physics=args.physics)
    cfg = build(run_config("evolution", setup)).fitness  # the Crawler study's fitness
    near = neighbourhood(space)
    start = time.time()
    found = em.confirm(space, em.stack([m for _, m in near.values()]), jax.random.PRNGKey(7),
                       cfg, args.controllers, ranked=False)
    device = jax.devices()[0]
    data = {"space": "crawler", "task": "walk", "physics": args.physics,
            "train_steps": args.train_steps, "controllers": args.controllers,
            "device": f"{device.platform}: {device.device_kind}",
            "device_seconds": round(time.time() - start, 1),
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "revision": revision(),
            "bodies": [{"name": name, "body": body, "mean": c.mean, "ci95": list(c.ci95),
                        "values": [float(v) for v in c.values],
                        "distance": float(np.mean(c.distance)), "upright_whole": c.upright_whole}
                       for (body, (name, _)), c in zip(near.items(), found, strict=True)]}
    for b in data["bodies"]:
        print(f"{b['name']:>28}: {b['mean']:6.1f} [{b['ci95'][0]:.1f}, {b['ci95'][1]:.1f}], "
              f"{b['distance']:.2f} m  {b['body']}")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "crawler_valley.json").write_text(json.dumps(data, indent=1))
    print(f"wrote {args.out / 'crawler_valley.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
