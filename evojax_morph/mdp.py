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
REMEASURE = -1  # an action outside the mask: no mutation, the body evaluated again


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
    fitness_std: jax.Array  # (N,): spread of that fitness (over the K controllers, or episodes)
    diverged: jax.Array  # (N,) bool: a simulation of the evaluation diverged
    distance: jax.Array  # (N,): metres forward in the evaluation episodes (NaN: none run)
    upright: jax.Array  # (N,): the fraction of those episodes before a fall
    steps: jax.Array  # (N,) int32: mutations done this episode


@dataclasses.dataclass(frozen=True)
class EvolutionEnv:
    """`num_envs` parallel evolutions of `space` under a batched `fitness_fn`
    (`fitnesses.batched.make_env` builds one from a fitness config).

    Attributes:
      space: the space the bodies belong to.
      fitness_fn: fitness_fn(keys (N,), morphs (N, ...), params (N, ...)) -> `FitnessResult`
        of (N,) arrays and the trained controllers (`fitnesses.batched.make_fitness_fn`).
      init_fn: init_fn(key) -> one controller.
      horizon: mutations an episode; an ended episode restarts from m0.
      num_envs: N, the parallel evolutions a step mutates and evaluates.
      reward_scale: what a run's agent multiplies the rewards by before learning: 1 over the
        typical size of the fitness's values (`fitnesses.Fitness.scale`).
    """

    space: Space
    fitness_fn: Callable
    init_fn: Callable
    horizon: int
    num_envs: int
    reward_scale: float = 1.0

    def observe(self, state: EvoState) -> Observation:
        mask = jax.vmap(self.space.action_mask)(state.morph).reshape(self.num_envs, -1)
        return Observation(state.morph, mask, state.steps / self.horizon)

    def reset(self, key: jax.Array) -> tuple[Observation, EvoState]:
        """Every env at m0, its controller trained from scratch and its fitness measured."""
        keys, morphs, params = self.first_bodies(key)
        return self.first_evaluated(morphs, self.fitness_fn(keys, morphs, params))

    def first_bodies(self, key: jax.Array):
        """The first half of `reset`: its fitness call's arguments, (keys (N,), m0 N times,
        fresh controllers (N, ...))."""
        key_init, key_fit = jax.random.split(key)
        morph = jax.tree.map(
            lambda x: jnp.broadcast_to(x, (self.num_envs,) + x.shape), self.space.initial()
        )
        params = jax.vmap(self.init_fn)(jax.random.split(key_init, self.num_envs))
        return jax.random.split(key_fit, self.num_envs), morph, params

    def first_evaluated(self, morphs: Morphology, out) -> tuple[Observation, EvoState]:
        """The second half of `reset`: m0 (`morphs`) evaluated as `out`."""
        state = self._evaluated(morphs, out, jnp.zeros(self.num_envs, jnp.int32))
        return self.observe(state), state

    @staticmethod
    def _evaluated(morph: Morphology, out, steps: jax.Array) -> EvoState:
        return EvoState(morph, out.params, out.fitness, out.fitness_std, out.diverged,
                        out.distance, out.upright, steps)

    def step(self, key: jax.Array, state: EvoState, action: jax.Array):
        """Mutate every env's body, evaluate the children in one batch.

        An env whose action is `REMEASURE` keeps its body: its child is the same body evaluated
        again (its controller trained further, for the PPO fitness). Only the baselines' own
        selection asks for it; a learning agent chooses valid mutations.

        Returns (obs, state, reward, terminated, truncated, info); an env whose episode ended
        is not reset here: `auto_reset` does that, so a caller can see the final state.
        """
        keys, morphs, params = self.children(key, state, action)
        return self.evaluated(state, action, morphs, self.fitness_fn(keys, morphs, params))

    def children(self, key: jax.Array, state: EvoState, action: jax.Array):
        """The first half of `step`: the fitness call's arguments, (keys (N,), the children's
        morphs (N, ...), the controllers they inherit (N, ...)). A study (`study`) evaluates
        several envs' children in one call."""
        nm = self.space.num_mutations
        valid = jnp.maximum(action, 0)
        mutated = jax.vmap(self.space.mutate)(state.morph, valid // nm, valid % nm)
        child = tree_select(action == REMEASURE, state.morph, mutated)
        return jax.random.split(key, self.num_envs), child, state.params

    def evaluated(self, state: EvoState, action: jax.Array, morphs: Morphology, out):
        """The second half of `step`: the children `morphs` of `action`, evaluated as `out`
        (the `FitnessResult` of `children`'s arguments) -> `step`'s returns."""
        del action  # what a subclass may check (tests/test_agent.py's RootOnlyEnv)
        new = self._evaluated(morphs, out, state.steps + 1)
        terminated = new.steps >= self.horizon
        truncated = jnp.zeros_like(terminated)
        return self.observe(new), new, new.fitness - state.fitness, terminated, truncated, {}

    def auto_reset(self, state: EvoState, first: EvoState, done: jax.Array) -> EvoState:
        """Envs whose episode ended start again from `first` (m0 as `reset` evaluated it)."""
        return tree_select(done, first, state)


def track_best(evo: EvoState, best=None):
    """The best (fitness, morphology, controller) so far, updated with this step's bodies; with
    no best so far (`best` None), the best of `evo`."""
    if best is None:
        best = (-jnp.inf,) + jax.tree.map(lambda x: x[0], (evo.morph, evo.params))
    i = jnp.argmax(evo.fitness)
    improved = evo.fitness[i] > best[0]
    new = jax.tree.map(lambda x: x[i], (evo.fitness, evo.morph, evo.params))
    return jax.tree.map(lambda n, o: jnp.where(improved, n, o), new, tuple(best))


def masked_argmax(scores: jax.Array, mask: jax.Array) -> jax.Array:
    """(...,) int: the best valid action of (..., A) scores under an (..., A) mask."""
    return jnp.argmax(jnp.where(mask, scores, NEG), axis=-1)


def random_valid_actions(key: jax.Array, mask: jax.Array) -> jax.Array:
    """(N,) int32: one uniformly random valid action per row of an (N, A) mask."""
    return jax.random.categorical(key, jnp.where(mask, 0.0, NEG)).astype(jnp.int32)
