"""What a fitness call returns for a batch of bodies: `FitnessResult`.

It sits below both the PPO trainer (`evojax_morph.ppo`), which returns it, and the fitness
kinds (`evojax_morph.fitnesses`), which return it from every `evaluate`.
"""

from __future__ import annotations

from typing import Any

import jax
from flax import struct


@struct.dataclass
class FitnessResult:
    """What a fitness call returns for a batch of B bodies (`em.evaluate`). The gait, `distance`
    and `upright`, is of the evaluation episodes: NaN for a kind that runs none (predefined,
    TAME) and a table built without them.

    Attributes:
      fitness: (B,) float: the fitness of each morphology
      fitness_std: (B,) float: spread across evaluation episodes (0 if deterministic)
      diverged: (B,) bool: a simulation diverged; its fitness is finite but suspect
      params: batched (B, ...) trained controllers; None for kinds without one
      train_return: (B,) mean over envs of the last finished training episode's return
      entropy: (B,) policy entropy per motor at the end of training
      distance: (B,) metres the trunk moved forward in an episode, mean
      upright: (B,) the fraction of an episode before a fall, mean (1: never fell)
      env_steps: control steps spent per morphology
    """

    fitness: jax.Array  # (B,) float
    fitness_std: jax.Array  # (B,) float
    diverged: jax.Array  # (B,) bool
    params: Any  # (B, ...) pytree: `ppo.Params` for PPO; None for kinds without one
    train_return: jax.Array  # (B,) float
    entropy: jax.Array  # (B,) float
    distance: jax.Array  # (B,) float
    upright: jax.Array  # (B,) float
    env_steps: int = struct.field(pytree_node=False)
