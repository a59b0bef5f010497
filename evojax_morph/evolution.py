"""Evolution as a Markov Decision Process, functional and gym-like.

State: a morphology, its controller (inherited by its children) and its fitness. Action: one
(node, mutation) pair, flattened to node * num_mutations + mutation, with the valid ones in the
observation's mask. Reward: f(child) - f(parent), so with discount 1 the return is f_k - f_0.
Episodes last `horizon` mutations. Fitness is a pluggable batched function, and every env call
takes a batch of parallel unrolls, so one step evaluates a whole batch of morphologies.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from evojax_morph.morphology import Morphology, tree_select
from evojax_morph.spaces import Space

NEG = -1e9  # the score of a masked action: large and finite, never -inf


@struct.dataclass
class Observation:
    morph: Morphology  # (N, max_nodes, ...)
    mask: jax.Array  # (N, num_actions) bool: valid actions
    progress: jax.Array  # (N,) float: mutations done / horizon


@struct.dataclass
class EvoState:
    morph: Morphology  # (N, ...) current bodies
    params: Any  # (N, ...) their controllers
    fitness: jax.Array  # (N,)
    steps: jax.Array  # (N,) int32: mutations done this episode


@dataclasses.dataclass(frozen=True)
class EvolutionEnv:
    """`num_envs` parallel evolutions of `space` under a batched `fitness_fn`.

    fitness_fn(keys (N,), morphs (N, ...), params (N, ...)) -> (fitness (N,), params (N, ...)),
    e.g. from `fitness.make_fitness_fn`; init_fn(key) -> one controller.
    """

    space: Space
    fitness_fn: Callable
    init_fn: Callable
    horizon: int
    num_envs: int

    def observe(self, state: EvoState) -> Observation:
        mask = jax.vmap(self.space.action_mask)(state.morph).reshape(self.num_envs, -1)
        return Observation(state.morph, mask, state.steps / self.horizon)

    def reset(self, key: jax.Array) -> tuple[Observation, EvoState]:
        """Every env at m0, its controller trained from scratch and its fitness measured."""
        key_init, key_fit = jax.random.split(key)
        morph = jax.tree.map(
            lambda x: jnp.broadcast_to(x, (self.num_envs,) + x.shape), self.space.initial()
        )
        params = jax.vmap(self.init_fn)(jax.random.split(key_init, self.num_envs))
        fitness, params = self.fitness_fn(jax.random.split(key_fit, self.num_envs), morph, params)
        state = EvoState(morph, params, fitness, jnp.zeros(self.num_envs, jnp.int32))
        return self.observe(state), state

    def step(self, key: jax.Array, state: EvoState, action: jax.Array):
        """Mutate every env's body, evaluate the children in one batch.

        Returns (obs, state, reward, terminated, truncated, info); an env whose episode ended
        is not reset here: `auto_reset` does that, so a caller can see the final state.
        """
        nm = self.space.num_mutations
        child = jax.vmap(self.space.mutate)(state.morph, action // nm, action % nm)
        fitness, params = self.fitness_fn(jax.random.split(key, self.num_envs), child, state.params)
        steps = state.steps + 1
        new = EvoState(child, params, fitness, steps)
        terminated = steps >= self.horizon
        truncated = jnp.zeros_like(terminated)
        return self.observe(new), new, fitness - state.fitness, terminated, truncated, {}

    def auto_reset(self, state: EvoState, first: EvoState, done: jax.Array) -> EvoState:
        """Envs whose episode ended start again from `first` (m0 as `reset` evaluated it)."""
        return tree_select(done, first, state)


def track_best(evo: EvoState, best_fitness=-jnp.inf, best_morph: Morphology | None = None):
    """The best (fitness, morphology) so far, updated with this step's bodies; with no best so
    far, the best of `evo`."""
    if best_morph is None:
        best_morph = jax.tree.map(lambda x: x[0], evo.morph)
    best = jnp.argmax(evo.fitness)
    improved = evo.fitness[best] > best_fitness
    morph = jax.tree.map(
        lambda new, old: jnp.where(improved, new[best], old), evo.morph, best_morph
    )
    return jnp.where(improved, evo.fitness[best], best_fitness), morph


def masked_argmax(scores: jax.Array, mask: jax.Array) -> jax.Array:
    """(...,) int: the best valid action of (..., A) scores under an (..., A) mask."""
    return jnp.argmax(jnp.where(mask, scores, NEG), axis=-1)


def random_valid_actions(key: jax.Array, mask: jax.Array) -> jax.Array:
    """(N,) int32: one uniformly random valid action per row of an (N, A) mask."""
    return jax.random.categorical(key, jnp.where(mask, 0.0, NEG)).astype(jnp.int32)
