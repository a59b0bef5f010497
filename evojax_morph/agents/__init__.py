"""Agents that choose mutations, registered by name, all with one skeleton (`agents.base`).

`make_agent(name, env)` returns an `Agent(init, chunk, scores)`: init(key) -> `AgentState`;
chunk(state, n) runs n environment steps (each evaluates env.num_envs children) in one jitted
scan and stacks per-step metrics ("reward" and "fitness" of shape (n, N), "best_fitness" (n,),
"bodies": the children evaluated and their parents, for the body log; and the agent's own,
e.g. "epsilon", "entropy", "loss"); scores(learner, obs) -> (N, A) scores whose masked argmax
is the greedy action, or None for the baselines, which learn nothing. `ask_tell(name, env)`
gives the same agent with the caller evaluating its children (`AskTell`).

To add an agent: a module of this package with its config dataclass (its defaults; each field
becomes the run command's `--agent.FIELD`; optionally `for_run`, what a run's shared
`RunOptions` make of it, and `check(num_envs)`) and `make_policy(env, cfg) -> Policy` (how it
acts and learns), and a line in `_REGISTRY`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax

from evojax_morph.agents import a2c, baselines, dqn, predictor, qrdqn
from evojax_morph.agents.base import (
    Agent,
    AgentState,
    AskTell,
    Policy,
    Proposal,
    RunOptions,
    Start,
    Transition,
    from_policy,
    make_ask_tell,
)
from evojax_morph.mdp import EvolutionEnv
from evojax_morph.registry import Registry


class AgentKind(NamedTuple):
    """A registered agent: its name, its config dataclass (None: nothing to set), its policy
    and its check of a run's settings."""

    name: str  # what `make_agent` and the CLI's --agent call it
    config: type | None
    make_policy: Callable  # make_policy(env, cfg) -> Policy
    check: Callable | None = None  # check(num_envs): ValueError where an agent without
    # settings cannot run num_envs evolutions (one with settings: its config's `check`)


_REGISTRY: Registry[AgentKind] = Registry("agent", (
    AgentKind("ddqn", dqn.DQNConfig, dqn.make_policy),
    AgentKind("dqn", dqn.PlainDQNConfig, dqn.make_policy),
    AgentKind("qrdqn", qrdqn.QRDQNConfig, qrdqn.make_policy),
    AgentKind("bootdqn", dqn.BootstrappedDQNConfig, dqn.make_policy),
    AgentKind("a2c", a2c.A2CConfig, a2c.make_policy),
    AgentKind("random", None, baselines.make_random),
    AgentKind("evolution", None, baselines.make_evolution, baselines.check_evolution),
    AgentKind("regularized_evolution", baselines.RegularizedEvolutionConfig,
              baselines.make_regularized_evolution),
    AgentKind("predictor", predictor.PredictorConfig, predictor.make_policy),
))


def list_agents() -> list[str]:
    """Names accepted by `make_agent`, in the order the CLI lists them."""
    return _REGISTRY.list()


def get_agent(name: str) -> AgentKind:
    """The agent registered as `name`."""
    return _REGISTRY.get(name)


def settings_problem(name: str, num_envs: int, params: dict | None = None,
                     shared: dict | None = None) -> str | None:
    """Why agent `name` cannot run `num_envs` evolutions with its own `params` (fields of its
    config) set over the run's `shared` settings it has a field for (`RunOptions`' by name:
    population, tournament, ...); None: it can. Its config's `check(num_envs)` says, or for an
    agent without settings `AgentKind.check`; called before anything compiles."""
    kind, params = get_agent(name), params or {}
    try:
        if kind.config is None:
            if params:
                raise ValueError(f"the {name} agent has no settings")
            if kind.check is not None:
                kind.check(num_envs)
            return None
        fields = {f.name for f in dataclasses.fields(kind.config)}
        config = dataclasses.replace(kind.config(), **{
            k: v for k, v in (shared or {}).items() if k in fields} | params)
        if hasattr(config, "check"):
            config.check(num_envs)
    except ValueError as e:
        return str(e)
    return None


def config_for_run(name: str, env: EvolutionEnv, run: RunOptions, params: dict | None = None
                   ) -> Any:
    """The config of agent `name` that a run's shared settings give it (None for the baselines
    without settings; a config without `for_run` takes none of them), then its own `params`
    (fields of its config) set over it; one named as a `RunOptions` field goes in before the
    defaults resolve, so that `population` alone resolves the tournament from it."""
    config = get_agent(name).config
    if config is None:
        return None
    params = params or {}
    run = run._replace(**{k: v for k, v in params.items() if k in RunOptions._fields})
    config = config.for_run(env, run) if hasattr(config, "for_run") else config()
    return dataclasses.replace(config, **params) if params else config


def make_policy(name: str, env: EvolutionEnv, cfg: Any = None, run: RunOptions | None = None,
                **overrides) -> Policy:
    """How agent `name` acts and learns on `env` (see `Policy`).

    cfg: its config; default: what a run's shared settings `run` give it (`config_for_run`),
      or without `run` the config's defaults. `overrides` replace fields of it (with `run`
      and no `cfg`, as `config_for_run`'s `params`).
    """
    kind = get_agent(name)
    if cfg is None and run is not None:
        cfg, overrides = config_for_run(name, env, run, overrides), {}
    if kind.config is not None:
        cfg = dataclasses.replace(kind.config() if cfg is None else cfg, **overrides)
    elif cfg is not None or overrides:
        raise ValueError(f"the {name} agent has no settings")
    return kind.make_policy(env, cfg)


def make_agent(name: str, env: EvolutionEnv, cfg: Any = None, mesh=None,
               run: RunOptions | None = None, **overrides) -> Agent:
    """The agent `name` on `env`, jitted, its state replicated on `mesh` (default: every
    device); `cfg`, `run` and `overrides` as in `make_policy`."""
    policy = make_policy(name, env, cfg, run, **overrides)
    return from_policy(env, policy, mesh)


def ask_tell(name: str, env: EvolutionEnv, cfg: Any = None, **overrides) -> AskTell:
    """Agent `name` on `env` with the caller evaluating its children, each part jitted
    (`AskTell`); `cfg` and `overrides` as in `make_policy`. Its steps are `make_agent`'s:
    asked, evaluated by `env.fitness_fn` and told, they give what `chunk` gives."""
    parts = make_ask_tell(env, make_policy(name, env, cfg, **overrides))
    return AskTell(*(jax.jit(f) for f in parts))


__all__ = [
    "Agent",
    "AgentState",
    "AskTell",
    "Policy",
    "Proposal",
    "RunOptions",
    "Start",
    "Transition",
    "ask_tell",
    "config_for_run",
    "get_agent",
    "settings_problem",
    "from_policy",
    "list_agents",
    "make_agent",
    "make_policy",
]
