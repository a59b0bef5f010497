"""Exhaustive fitness landscapes: every body reachable from m0, measured over several seeds.

Bodies are those of `Space.enumerate_bodies`, told apart by `Space.canonical`, which ignores slot
numbers and sibling order: two bodies are the same when their trees of (kind, site, attributes)
are, so Bad Walker's two identical short feet swapped give one body. A `Landscape` stores each
body's mean and std of fitness and answers the rank and regret of any body an agent finds.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import numpy as np

from evojax_morph.fitness import FitnessConfig, evaluate
from evojax_morph.morphology import Morphology, stack
from evojax_morph.spaces import Space, make_space


@dataclasses.dataclass
class Landscape:
    """Fitness of every enumerated body of a space: (K,) arrays in `enumerate_bodies` order."""

    space: str
    keys: list[str]  # canonical names
    bodies: list[dict]  # Morphology.to_dict()
    depths: list[int]
    mean: np.ndarray  # (K,)
    std: np.ndarray  # (K,) across seeds
    seeds: int
    config: dict  # how fitness was measured

    def index(self, m: Morphology) -> int:
        key = make_space(self.space).canonical(m)
        if key not in self.keys:
            raise KeyError(
                f"body not in the {self.space} landscape (deeper than it was enumerated?)"
            )
        return self.keys.index(key)

    def rank(self, m: Morphology) -> int:
        """1 for the body with the highest mean fitness; ties share the better rank."""
        return int(np.sum(self.mean > self.mean[self.index(m)])) + 1

    def regret(self, m: Morphology) -> float:
        """Best mean fitness in the landscape minus this body's."""
        return float(self.mean.max() - self.mean[self.index(m)])

    def best(self) -> Morphology:
        return Morphology.from_dict(self.bodies[int(np.argmax(self.mean))])

    def save(self, path) -> None:
        d = dataclasses.asdict(self)
        d["mean"], d["std"] = self.mean.tolist(), self.std.tolist()
        Path(path).write_text(json.dumps(d))

    @classmethod
    def load(cls, path) -> Landscape:
        d = json.loads(Path(path).read_text())
        d["mean"], d["std"] = np.asarray(d["mean"]), np.asarray(d["std"])
        return cls(**d)


def measure(
    space: Space,
    cfg: FitnessConfig,
    seeds: int,
    key: jax.Array,
    max_depth: int | None = None,
    batch: int = 1024,
) -> Landscape:
    """Enumerates the space and evaluates every body `seeds` times, from scratch, in batches.

    Args:
      space: the space.
      cfg: the fitness and its budget (a long PPO budget ranks bodies by how well they can walk).
      seeds: independent evaluations per body (different keys, fresh controllers).
      key: PRNG key; evaluation s of body k uses fold_in(fold_in(key, k), s).
      max_depth: mutations from m0 to enumerate (None: all).
      batch: morphologies per compiled call.
    """
    bodies, depths = space.enumerate_bodies(max_depth)
    jobs = [(k, s) for k in range(len(bodies)) for s in range(seeds)]
    fitness = np.zeros((len(bodies), seeds))
    for start in range(0, len(jobs), batch):
        part = jobs[start : start + batch]
        part = part + [part[0]] * (batch - len(part)) if len(jobs) > batch else part  # one shape
        keys = jax.numpy.stack([jax.random.fold_in(jax.random.fold_in(key, k), s) for k, s in part])
        out = np.asarray(evaluate(space, stack([bodies[k] for k, _ in part]), keys, cfg).fitness)
        for (k, s), f in zip(part[: len(jobs) - start], out):
            fitness[k, s] = f
    return Landscape(
        space=space.name,
        keys=[space.canonical(m) for m in bodies],
        bodies=[m.to_dict() for m in bodies],
        depths=depths,
        mean=fitness.mean(1),
        std=fitness.std(1),
        seeds=seeds,
        config={
            "kind": cfg.kind,
            "train_steps": cfg.ppo.train_steps,
            "num_envs": cfg.ppo.num_envs,
            "max_depth": max_depth,
        },
    )
