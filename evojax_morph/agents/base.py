"""The skeleton every agent shares: its state, `init`, and the scanned, replicated step loop.

An agent states only how it acts and how it learns (a `Policy`); `from_policy` wraps that in the
loop observe -> act -> mutate -> evaluate (one fitness call) -> track the best body -> restart
ended episodes -> learn, run `num_steps` times in one jitted `lax.scan` per chunk.
`make_ask_tell` gives the same step split around its fitness call, the caller evaluating
(evosax's ask/tell): a user's own loop, and a study that evaluates several agents' children
in one call (`evojax_morph.search.study`), step an agent through it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from evojax_morph.mdp import EvolutionEnv, EvoState, Observation, track_best
from evojax_morph.morphology import Morphology
from evojax_morph.sharding import jit_replicated


@struct.dataclass
class AgentState:
    """What every agent carries between steps; `learner` is the agent's own."""

    learner: Any  # the agent's networks, optimiser and memory (None for the baselines)
    evo: EvoState  # (N, ...) the parallel evolutions
    first: EvoState  # (N, ...) m0 as reset evaluated it, where ended episodes restart
    key: jax.Array
    step: jax.Array  # () int32: env steps done
    best_fitness: jax.Array  # (): best fitness seen in any env
    best_morph: Morphology  # the body that had it
    best_params: Any  # the controller it was evaluated with (trained, for the PPO fitness)


class RunOptions(NamedTuple):
    """What a run sets for whichever agent it runs; each agent's config takes its share
    (`for_run`)."""

    hidden: int  # GNN width
    explore_steps: int  # environment steps of exploration (ddqn: epsilon's annealing)
    learning_starts: int  # transitions stored before learning (ddqn)
    population: int = 0  # regularized_evolution: members (0: its default)
    tournament: int = 0  # regularized_evolution: members sampled per tournament (0: default)


class Transition(NamedTuple):
    """One environment step of N evolutions, as `Policy.learn` sees it."""

    obs: Observation  # (N, ...) before the step
    action: jax.Array  # (N,) int32
    reward: jax.Array  # (N,) f(child) - f(parent), unscaled
    next_obs: Observation  # (N, ...) after the step, before ended episodes restart
    terminated: jax.Array  # (N,) bool
    done: jax.Array  # (N,) bool: terminated or truncated


def bodies(parents: EvoState, children: EvoState) -> dict:
    """What the body log keeps of one step: every child evaluated, with its parent."""
    return {"parent": parents.morph, "morph": children.morph, "fitness": children.fitness,
            "fitness_std": children.fitness_std, "diverged": children.diverged,
            "distance": children.distance, "upright": children.upright}


def _restart(env: EvolutionEnv, learner, keys, parents: EvoState, children: EvoState,
             first: EvoState, done):
    del keys, parents
    return learner, env.auto_reset(children, first, done)


class Policy(NamedTuple):
    """How one agent acts and learns; `from_policy` supplies everything else.

    keys: PRNG keys taken by (init, act, learn[, next_evo]) each call, split off the agent's
      key in one call (init: [init keys..., env, next]; step: [next, act keys..., env, learn
      keys..., next_evo keys...]).
    init(keys, obs) -> learner: the agent's own state, from the first (N, ...) observation.
    act(learner, keys, obs, step) -> (action (N,) int32, metrics): valid actions only.
    learn(learner, keys, transition, step) -> (learner, metrics).
    scores(learner, obs) -> (N, num_actions): whose masked argmax is the greedy action; None
      for an agent without a policy to roll out.
    next_evo(env, learner, keys, parents, children, first, done) -> (learner, the bodies the
      next step mutates); default: the children, with ended episodes restarted at `first`.
      The baselines select here (a population kept in `learner`).
    """

    keys: tuple[int, ...]
    init: Callable
    act: Callable
    learn: Callable
    scores: Callable | None
    next_evo: Callable = _restart


class Agent(NamedTuple):
    """init(key) -> AgentState; chunk(state, num_steps) -> (state, metrics stacked over steps):
    "reward" and "fitness" (num_steps, N), "best_fitness" (num_steps,), "bodies" (every child
    evaluated and its parent, see `bodies`) and the agent's own;
    scores(learner, obs) -> (N, num_actions) or None (see `Policy`)."""

    init: Callable
    chunk: Callable
    scores: Callable | None


class Proposal(NamedTuple):
    """What `AskTell.ask` returns and `AskTell.tell` takes back: the children to evaluate, as
    the fitness call's arguments (`keys`, `morphs`, `params`), and what acting chose."""

    keys: jax.Array  # (N,) the fitness call's keys
    morphs: Morphology  # (N, ...) the children
    params: Any  # (N, ...) the controllers they inherit
    obs: Observation  # (N, ...) what the agent acted on
    action: jax.Array  # (N,) int32
    key_learn: jax.Array  # (n_learn, 2) the keys `Policy.learn` takes
    key_next: jax.Array  # (n_next, 2) the keys `Policy.next_evo` takes
    key: jax.Array  # the agent's key for the step after
    act_metrics: dict  # `Policy.act`'s metrics


class Start(NamedTuple):
    """What `AskTell.ask_first` returns and `AskTell.tell_first` takes back: m0's
    evaluation, as the fitness call's arguments (`keys`, `morphs`, `params`), and the keys
    left."""

    keys: jax.Array  # (N,) the fitness call's keys
    morphs: Morphology  # (N, ...) m0, N times
    params: Any  # (N, ...) fresh controllers
    key_init: jax.Array  # (n_init, 2) the keys `Policy.init` takes
    key: jax.Array  # the agent's key for its first step


class AskTell(NamedTuple):
    """An agent's loop with the caller evaluating (`make_ask_tell`; jitted: `agents.ask_tell`).

    `out` below is the `FitnessResult` of `fitness(keys, morphs, params)` of what was asked,
    by any function that evaluates as `env.fitness_fn` does (`em.evaluate(space, morphs,
    keys, cfg, params)` outside a jitted loop). The agent's key lives in its state, so `ask`
    takes none: the same state asks for the same children.

    Attributes:
      init: init(key) -> `AgentState`: ask_first and tell_first with the env's own fitness.
      ask_first: ask_first(key) -> `Start`: m0, N times with fresh controllers, to evaluate.
      tell_first: tell_first(start, out) -> `AgentState`: the agent started on m0's
        evaluation.
      ask: ask(state) -> `Proposal`: act and mutate; the N children to evaluate.
      tell: tell(state, proposal, out) -> (state, metrics): the children's rewards, the best
        body tracked, ended episodes restarted, the agent learned; metrics "reward",
        "fitness", "best_fitness", "bodies" and the agent's own, as `Agent.chunk`'s for one
        step.
    """

    init: Callable
    ask_first: Callable
    tell_first: Callable
    ask: Callable
    tell: Callable


def make_ask_tell(env: EvolutionEnv, policy: Policy) -> AskTell:
    """The loop of `policy` on `env`, split around its fitness calls (`AskTell`)."""
    n_init, n_act, n_learn, n_next = (*policy.keys, 0)[:4]

    def ask_first(key: jax.Array) -> Start:
        keys = jax.random.split(key, n_init + 2)
        return Start(*env.first_bodies(keys[n_init]), keys[:n_init], keys[n_init + 1])

    def tell_first(first: Start, out) -> AgentState:
        obs, evo = env.first_evaluated(first.morphs, out)
        learner = policy.init(first.key_init, obs)
        return AgentState(learner, evo, evo, first.key, jnp.zeros((), jnp.int32),
                          *track_best(evo))

    def init(key: jax.Array) -> AgentState:
        first = ask_first(key)
        return tell_first(first, env.fitness_fn(first.keys, first.morphs, first.params))

    def ask(state: AgentState) -> Proposal:
        keys = jax.random.split(state.key, n_act + n_learn + n_next + 2)
        key_act, key_env = keys[1 : 1 + n_act], keys[1 + n_act]
        key_learn, key_next = jnp.split(keys[2 + n_act :], [n_learn])

        # ACT on valid actions only
        obs = env.observe(state.evo)
        action, act_metrics = policy.act(state.learner, key_act, obs, state.step)

        # MUTATE: the children, to be evaluated in one batched fitness call
        fit_keys, morphs, params = env.children(key_env, state.evo, action)
        return Proposal(fit_keys, morphs, params, obs, action, key_learn, key_next, keys[0],
                        act_metrics)

    def tell(state: AgentState, prop: Proposal, out):
        # THE CHILDREN EVALUATED
        next_obs, children, reward, terminated, truncated, _ = env.evaluated(
            state.evo, prop.action, prop.morphs, out)
        best = track_best(children, (state.best_fitness, state.best_morph, state.best_params))
        done = terminated | truncated
        learner, evo = policy.next_evo(env, state.learner, prop.key_next, state.evo, children,
                                       state.first, done)

        # LEARN
        transition = Transition(prop.obs, prop.action, reward, next_obs, terminated, done)
        learner, learn_metrics = policy.learn(learner, prop.key_learn, transition, state.step)
        new = AgentState(learner, evo, state.first, prop.key, state.step + 1, *best)
        metrics = {"reward": reward, "fitness": children.fitness, "best_fitness": best[0]}
        metrics["bodies"] = bodies(state.evo, children)
        return new, {**metrics, **prop.act_metrics, **learn_metrics}

    return AskTell(init, ask_first, tell_first, ask, tell)


def from_policy(env: EvolutionEnv, policy: Policy, mesh=None) -> Agent:
    """The jitted agent of `policy` on `env`, its state replicated on `mesh` (default: every
    device; the fitness inside splits its batch across them)."""
    steps = make_ask_tell(env, policy)

    def env_step(state: AgentState, _):
        prop = steps.ask(state)
        return steps.tell(state, prop, env.fitness_fn(prop.keys, prop.morphs, prop.params))

    def chunk(state: AgentState, num_steps: int):
        """`num_steps` env steps in one `lax.scan`; metrics stacked along a leading axis."""
        return jax.lax.scan(env_step, state, length=num_steps)

    init, chunk = jit_replicated(steps.init, chunk, mesh)
    return Agent(init, chunk, policy.scores)
