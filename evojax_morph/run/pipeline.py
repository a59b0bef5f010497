"""A whole run assembled from its config: space -> fitness -> evolution env -> agent.

`build(cfg)` is the one place that puts a run together: the `run` command, the experiments and
the tests that need a whole pipeline all call it. The greedy rollout reads a trained agent's
choices from m0.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from evojax_morph import agents
from evojax_morph.agents import Agent, RunOptions
from evojax_morph.fitnesses import FitnessConfig, Inputs, get_fitness, standard_ppo
from evojax_morph.fitnesses.batched import make_fitness_fn
from evojax_morph.mdp import EvolutionEnv, masked_argmax
from evojax_morph.sharding import batch_mesh, to_host
from evojax_morph.spaces import Space, make_space
from evojax_morph.tasks import make_task


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything that defines a run; saved as config.json, reloaded by --resume."""

    space: str = "bad_walker"
    fitness: str = "ppo"  # a registered fitness kind: ppo | predefined | tame | table
    task: str = ""  # the locomotion task (`list_tasks`): walk | distance; "": the fitness's default
    classifier: str = ""  # tame: directory of the trained classifier
    table: str = ""  # table: the landscape table (.npz); "": the space's packaged one
    agent: str = "ddqn"  # a registered agent (`agents.list_agents`)
    steps: int = 40  # environment steps; each mutates every parallel evolution once
    seed: int = 0
    num_envs: int = 4  # parallel evolutions, each step's fitness batch
    horizon: int = 0  # mutations per episode; 0: the space's default_horizon
    train_steps: int = 10_000  # PPO control steps per fitness evaluation (per controller)
    controllers: int = 1  # independent PPO controllers per body (table: draws); their mean
    physics: str = "jax"  # the engine of the fitness's worlds: jax | warp (`engines`)
    classes: bool = False  # ppo: each body on its size class's template (`classes`)
    hidden: int = 64  # GNN width
    explore_steps: int = 20  # (qr)dqn: environment steps over which epsilon anneals to 0.05
    learning_starts: int = 32  # (qr)dqn: transitions stored before the Q-network learns
    population: int = 0  # regularized_evolution: members; 0: 2 num_envs
    tournament: int = 0  # regularized_evolution: members sampled per tournament; 0: population/8
    chunk: int = 5  # environment steps per jitted call
    checkpoint_every: int = 1  # chunks between checkpoints
    confirm: int = 4  # bodies of the highest mean evaluated again at the end; 0: none
    confirm_controllers: int = 4  # fresh evaluations (controllers) per confirmed body


def agent_config(cfg: RunConfig, env: EvolutionEnv) -> Any:
    """The config of the run's agent that its settings give it (None for an agent without
    settings), its defaults resolved (`agents.config_for_run`)."""
    run = RunOptions(
        hidden=cfg.hidden,
        reward_scale=1.0 / get_fitness(cfg.fitness).scale(env.space),
        explore_steps=cfg.explore_steps,
        learning_starts=cfg.learning_starts,
        population=cfg.population,
        tournament=cfg.tournament,
    )
    return agents.config_for_run(cfg.agent, env, run)


class Pipeline(NamedTuple):
    """The parts of a run, bottom to top."""

    space: Space
    fitness: FitnessConfig
    init_fn: Callable  # init_fn(key) -> one controller (`fitness.make_fitness_fn`)
    fitness_fn: Callable  # fitness_fn(keys (N,), morphs (N, ...), params (N, ...))
    env: EvolutionEnv  # num_envs parallel evolutions
    agent: Agent  # init, chunk, scores
    greedy_env: EvolutionEnv  # the same with one evolution, for the greedy rollout


def build(cfg: RunConfig, mesh=None, agent_cfg: Any = None) -> Pipeline:
    """The run of `cfg`, its fitness batch and agent state on `mesh` (default: every device).

    agent_cfg: the agent's own config; default: what the run's settings give it
    (`agents.config_for_run`).
    """
    space = make_space(cfg.space)
    task = cfg.task or get_fitness(cfg.fitness).default_task(
        Inputs(cfg.space, classifier=cfg.classifier, table=cfg.table))
    fit_cfg = FitnessConfig(kind=cfg.fitness, task=make_task(task),
                            ppo=standard_ppo(cfg.train_steps, cfg.controllers),
                            classifier=cfg.classifier, physics=cfg.physics, table=cfg.table,
                            classes=cfg.classes)
    init_fn, fitness_fn = make_fitness_fn(space, fit_cfg, mesh)
    horizon = cfg.horizon or space.default_horizon
    env = EvolutionEnv(space, fitness_fn, init_fn, horizon=horizon, num_envs=cfg.num_envs)
    agent_cfg = agent_config(cfg, env) if agent_cfg is None else agent_cfg
    agent = agents.make_agent(cfg.agent, env, agent_cfg, mesh)
    # One body a call: the greedy rollout runs on one device of this process, a program with
    # no cross-device communication (split over 2 GPUs with Warp it hung, docs/benchmarks.md).
    one = make_fitness_fn(space, fit_cfg, batch_mesh(jax.local_devices()[:1]))[1]
    greedy_env = dataclasses.replace(env, num_envs=1, fitness_fn=one)
    return Pipeline(space, fit_cfg, init_fn, fitness_fn, env, agent, greedy_env)


class Greedy(NamedTuple):
    """A greedy rollout from m0: horizon + 1 bodies, m0 first."""

    morphs: list  # the bodies (`Morphology`, on the host)
    fitness: list[float]  # their fitness, each with a fresh controller (`make_greedy_rollout`)
    actions: list[str]  # the horizon mutations, named (`action_name`)
    params: list  # the controller each body was evaluated with (trained, for the PPO fitness)


NO_OP = " (no-op)"


def action_name(space, action: int, before, after) -> str:
    """"node 1: remove", with NO_OP appended where the body did not change (a mutation of the
    root that is a no-op, a move to where a limb already is)."""
    node, mutation = divmod(int(action), space.num_mutations)
    same = space.canonical(before) == space.canonical(after)
    return f"node {node}: {space.mutation_names[mutation]}" + (NO_OP if same else "")


def make_greedy_rollout(p: Pipeline):
    """`rollout(learner, first, key) -> Greedy`: from m0 (env 0 of `first`, the evaluated
    start), the agent's greedy mutations, then every body of the trajectory, m0 too, evaluated
    with a fresh controller in ONE fitness call. The mutations need no fitness (an observation
    is the body and the progress), so the horizon's bodies come first and their evaluations
    run side by side, not one body a call (one-body calls took 32 s for Bad Walker's 5 at
    50,000 PPO steps and 117 s for the Constructor's 8 at 100,000 on an H100, issue 61).
    A fresh controller (trained from scratch, as the confirm stage's) is the measurement
    the run's own steps are not: there a child inherits its parent's. Compiled once, reused
    across calls, on the first device of this process (`build`)."""
    space, env1, scores, init_fn = p.space, p.greedy_env, p.agent.scores, p.init_fn
    device = jax.local_devices()[0]

    @jax.jit
    def run(learner, evo, key):
        def body(evo, _):
            obs = env1.observe(evo)
            action = masked_argmax(scores(learner, obs), obs.mask)
            _, child, _ = env1.children(key, evo, action)
            return evo.replace(morph=child, steps=evo.steps + 1), (child, action[0])

        _, (morphs, actions) = jax.lax.scan(body, evo, length=env1.horizon)
        bodies = jax.tree.map(lambda m0, ms: jnp.concatenate([m0, ms[:, 0]]), evo.morph, morphs)
        key_init, key_fit = jax.random.split(key)
        n = env1.horizon + 1
        params = jax.vmap(init_fn)(jax.random.split(key_init, n))
        out = env1.fitness_fn(jax.random.split(key_fit, n), bodies, params)
        return bodies, out.params, out.fitness, actions

    env0 = lambda first: jax.tree.map(lambda x: x[:1], first)  # noqa: E731

    def on_device(learner, first, key):  # env 0 of `first`, with the rest, on `device`, by way
        # of the host: the agent's arrays may span the devices of several processes
        return jax.device_put(to_host((learner, env0(first), key)), device)

    def rollout(learner, first, key) -> Greedy:
        learner, first, key = on_device(learner, first, key)
        morphs, params, fitness, actions = to_host(run(learner, first, key))
        at = lambda tree, i: jax.tree.map(lambda x: x[i], tree)  # noqa: E731
        bodies = [at(morphs, i) for i in range(env1.horizon + 1)]
        names = [action_name(space, a, before, after)
                 for a, before, after in zip(actions, bodies, bodies[1:])]
        return Greedy(morphs=bodies, fitness=[float(f) for f in fitness], actions=names,
                      params=[at(params, i) for i in range(env1.horizon + 1)])

    def lower(learner, first, key):  # the abstract arguments (`driver._evolve_jobs`)
        place = lambda x: jax.ShapeDtypeStruct(  # noqa: E731
            x.shape, x.dtype, sharding=jax.sharding.SingleDeviceSharding(device))
        return run.lower(*jax.tree.map(place, (learner, jax.eval_shape(env0, first), key)))

    rollout.lower = lower  # its program, for compiling ahead (`compile_ahead`)
    return rollout
