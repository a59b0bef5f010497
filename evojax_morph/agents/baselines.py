"""Baselines that learn nothing, at the agents' cost: N fitness evaluations per step.

random: N random mutation walks; each step applies a uniformly random valid mutation to every
  walk, episodes of `horizon` mutations restart from m0, as the agents' do.
evolution: NGE-like (mu + lambda) evolution with a population of N: each step every member
  gets one random valid mutation, the children (their controllers inherited from the parents
  and trained further) are evaluated, and the fittest N of parents and children survive.
  It never restarts.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from evojax_morph.agents.base import Policy
from evojax_morph.evolution import EvolutionEnv, EvoState, random_valid_actions


def select(env: EvolutionEnv, parents: EvoState, children: EvoState, first, done) -> EvoState:
    """SELECTION: the fittest N of parents and children, episode counters kept at 0."""
    del first, done
    pool = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), parents, children)
    _, keep = jax.lax.top_k(pool.fitness, env.num_envs)
    return jax.tree.map(lambda x: x[keep], pool).replace(steps=jnp.zeros(env.num_envs, jnp.int32))


def make_policy(env: EvolutionEnv, cfg: None = None, *, selection: bool = False) -> Policy:
    """Uniformly random valid mutations; with `selection`, (mu + lambda) survival."""
    del env, cfg  # nothing to set
    policy = Policy(
        keys=(0, 1, 0),
        init=lambda keys, obs: None,
        act=lambda learner, keys, obs, step: (random_valid_actions(keys[0], obs.mask), {}),
        learn=lambda learner, keys, transition, step: (None, {}),
        scores=None,
    )
    return policy._replace(next_evo=select) if selection else policy
