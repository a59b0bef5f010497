"""Agents that choose mutations, all with one interface.

`make_agent(name, env, ...)` returns `(init(key) -> state, chunk(state, n) -> (state, metrics),
scores_fn)`: chunk runs n environment steps (each evaluates env.num_envs children) in one jitted
scan and stacks per-step metrics ("reward" and "fitness" of shape (n, N), "best_fitness" (n,),
and the agent's own, e.g. "epsilon", "entropy", "loss"); scores_fn(params, obs) -> (N, A)
scores whose masked argmax is the greedy action, or None for the baselines, which learn nothing.
"""

from __future__ import annotations

from evojax_morph.agents import a2c, baselines, dqn

AGENTS = ("ddqn", "a2c", "random", "evolution")


def make_agent(name: str, env, hidden: int = 64, reward_scale: float = 1.0, mesh=None, **overrides):
    """The agent `name` on `env`; `overrides` go to its config (DQNConfig or A2CConfig)."""
    if name == "ddqn":
        return dqn.make_agent(env, dqn.DQNConfig(hidden=hidden, reward_scale=reward_scale, **overrides), mesh)
    if name == "a2c":
        return a2c.make_agent(env, a2c.A2CConfig(hidden=hidden, reward_scale=reward_scale, **overrides), mesh)
    if name in ("random", "evolution"):
        return baselines.make_agent(env, name, mesh)
    raise ValueError(f"unknown agent {name!r}; choose one of {', '.join(AGENTS)}")
