"""Agents that choose mutations, registered by name, all with one interface.

`make_agent(name, env, ...)` returns `(init(key) -> state, chunk(state, n) -> (state, metrics),
scores_fn)`: chunk runs n environment steps (each evaluates env.num_envs children) in one jitted
scan and stacks per-step metrics ("reward" and "fitness" of shape (n, N), "best_fitness" (n,),
and the agent's own, e.g. "epsilon", "entropy", "loss"); scores_fn(params, obs) -> (N, A)
scores whose masked argmax is the greedy action, or None for the baselines, which learn nothing.

To add an agent: a module of this package with its config dataclass and its `make_agent(env,
cfg, mesh)`, and a line in `_REGISTRY`.
"""

from __future__ import annotations

from collections.abc import Callable

from evojax_morph.agents import a2c, baselines, dqn


def _learner(config: type, make: Callable):
    """A learning agent's factory: its config built from the shared options and `overrides`."""

    def factory(env, hidden: int, reward_scale: float, mesh, **overrides):
        return make(env, config(hidden=hidden, reward_scale=reward_scale, **overrides), mesh)

    return factory


def _baseline(kind: str):
    def factory(env, hidden: int, reward_scale: float, mesh):
        del hidden, reward_scale  # nothing learns
        return baselines.make_agent(env, kind, mesh)

    return factory


_REGISTRY: dict[str, Callable] = {
    "ddqn": _learner(dqn.DQNConfig, dqn.make_agent),
    "a2c": _learner(a2c.A2CConfig, a2c.make_agent),
    "random": _baseline("random"),
    "evolution": _baseline("evolution"),
}


def list_agents() -> list[str]:
    """Names accepted by `make_agent`, in the order the CLI lists them."""
    return list(_REGISTRY)


def make_agent(name: str, env, hidden: int = 64, reward_scale: float = 1.0, mesh=None, **overrides):
    """The agent `name` on `env`; `overrides` go to its config (DQNConfig or A2CConfig)."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown agent {name!r}; choose one of {', '.join(_REGISTRY)}")
    return _REGISTRY[name](env, hidden, reward_scale, mesh, **overrides)
