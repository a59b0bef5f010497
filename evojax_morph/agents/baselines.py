"""Baselines that learn nothing, at the agents' cost: N fitness evaluations per step.

random: N random mutation walks; each step applies a uniformly random valid mutation to every
  walk, episodes of `horizon` mutations restart from m0, as the agents' do.
evolution: NGE-like (mu + lambda) evolution with a population of N: each step every member
  gets one random valid mutation, the children (their controllers inherited from the parents
  and trained further) are evaluated, and the fittest N of parents and children survive.
  It never restarts.
Both share the agents' interface: `make_agent(env) -> (init, chunk, None)`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from evojax_morph.evolution import EvolutionEnv, EvoState, random_valid_actions, track_best
from evojax_morph.sharding import jit_replicated


@struct.dataclass
class SearchState:
    evo: EvoState  # the walks, or the population
    first: EvoState  # m0 as reset evaluated it
    key: jax.Array
    step: jax.Array  # () int32
    best_fitness: jax.Array  # ()
    best_morph: object


def make_agent(env: EvolutionEnv, kind: str, mesh=None):
    """`kind` "random" or "evolution"; returns (init, chunk, None) like the learning agents."""
    if kind not in ("random", "evolution"):
        raise ValueError(f"unknown baseline {kind!r}")
    n = env.num_envs

    def init(key: jax.Array) -> SearchState:
        key_env, key = jax.random.split(key)
        _, evo = env.reset(key_env)
        return SearchState(evo, evo, key, jnp.zeros((), jnp.int32), *track_best(evo))

    def env_step(state: SearchState, _):
        key, key_act, key_env = jax.random.split(state.key, 3)
        action = random_valid_actions(key_act, env.observe(state.evo).mask)
        _, children, reward, terminated, truncated, _ = env.step(key_env, state.evo, action)
        best_fitness, best_morph = track_best(children, state.best_fitness, state.best_morph)
        if kind == "random":
            evo = env.auto_reset(children, state.first, terminated | truncated)
        else:  # SELECTION: the fittest n of parents and children, episode counters kept at 0
            pool = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), state.evo, children)
            _, keep = jax.lax.top_k(pool.fitness, n)
            evo = jax.tree.map(lambda x: x[keep], pool).replace(steps=jnp.zeros(n, jnp.int32))
        metrics = {"reward": reward, "fitness": children.fitness, "best_fitness": best_fitness}
        return SearchState(evo, state.first, key, state.step + 1, best_fitness, best_morph), metrics

    def chunk(state: SearchState, num_steps: int):
        return jax.lax.scan(env_step, state, length=num_steps)

    init, chunk = jit_replicated(init, chunk, mesh)
    return init, chunk, None
