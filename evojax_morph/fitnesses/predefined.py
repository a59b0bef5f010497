"""The space's own hand-crafted, deterministic fitness (`Space.predefined_fitness`)."""

from __future__ import annotations

import jax

from evojax_morph.fitnesses.base import Fitness, FitnessConfig, FitnessResult, untrained_result
from evojax_morph.spaces import Space


def make(space: Space, cfg: FitnessConfig):
    del cfg  # nothing to set

    def evaluate(keys: jax.Array, morphs, params) -> FitnessResult:
        fitness = jax.vmap(space.predefined_fitness)(morphs)
        return untrained_result(fitness, jax.numpy.zeros_like(fitness, bool), params, env_steps=0)

    return None, evaluate


FITNESS = Fitness(
    name="predefined",
    validate=lambda cfg: None,
    scale=lambda space: space.fitness_scale,
    make=make,
    deterministic=True,
    engines=(),
)
