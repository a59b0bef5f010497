"""A whole run assembled from its config: space -> fitness -> evolution env -> agent.

`build(cfg)` is the one place that puts a run together: the `run` command, the experiments and
the tests that need a whole pipeline all call it. Its greedy walk reads a trained agent's
choices from m0, and its greedy evaluation measures the bodies walked.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_morph import agents
from evojax_morph.agents import Agent, RunOptions
from evojax_morph.fitnesses import (
    FitnessConfig,
    Inputs,
    fitness_params,
    get_fitness,
    standard_ppo,
)
from evojax_morph.fitnesses.batched import make_env, make_fitness_fn
from evojax_morph.mdp import EvolutionEnv, masked_argmax
from evojax_morph.physics.engines import Engine, registered
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
    confirm_controllers: int = 4  # fresh evaluations per confirmed body (and greedy body with them)
    agent_params: dict = dataclasses.field(default_factory=dict)  # fields of the agent's config
    # set over what the flags above make of it (`--agent.FIELD`)
    fitness_params: dict = dataclasses.field(default_factory=dict)  # fields of the fitness
    # kind's settings set over their defaults (`Fitness.params`, `--fitness.FIELD`)
    task_params: dict = dataclasses.field(default_factory=dict)  # fields of the task's
    # settings set over the registered task's (`TaskConfig`, `--task.FIELD`)


def run_options(cfg: RunConfig) -> RunOptions:
    """The settings of `cfg` that each agent takes its share of (`RunOptions`)."""
    return RunOptions(
        hidden=cfg.hidden,
        explore_steps=cfg.explore_steps,
        learning_starts=cfg.learning_starts,
        population=cfg.population,
        tournament=cfg.tournament,
    )


def agent_config(cfg: RunConfig, env: EvolutionEnv) -> Any:
    """The config of the run's agent (None for an agent without settings): what the run's
    shared settings give it, `cfg.agent_params` set over it (`agents.config_for_run`), as
    `build` makes it."""
    return agents.config_for_run(cfg.agent, env, run_options(cfg), cfg.agent_params)


class Pipeline(NamedTuple):
    """The parts of a run, bottom to top."""

    space: Space
    fitness: FitnessConfig
    engine: Engine  # what the fitness's worlds step on (`cfg.physics`): its warmup, its preload
    init_fn: Callable  # init_fn(key) -> one controller (`fitness.make_fitness_fn`)
    fitness_fn: Callable  # fitness_fn(keys (N,), morphs (N, ...), params (N, ...))
    env: EvolutionEnv  # num_envs parallel evolutions
    agent: Agent  # init, chunk, scores
    greedy_env: EvolutionEnv  # the same with one evolution, for the greedy walk
    greedy_walk: Callable | None = None  # `make_greedy_walk`'s; None for the baselines: no
    # policy to roll out
    greedy_evaluation: Callable | None = None  # `make_greedy_evaluation`'s (None: baselines)


def build(cfg: RunConfig, mesh=None, agent_cfg: Any = None) -> Pipeline:
    """The run of `cfg`, its fitness batch and agent state on `mesh` (default: every device).

    agent_cfg: the agent's own config, `cfg.agent_params` set over it; default: what the
    run's settings give it (`agent_config`).
    """
    run = run_options(cfg)
    task = make_task(cfg.task or get_fitness(cfg.fitness).default_task(
        Inputs(cfg.space, classifier=cfg.classifier, table=cfg.table)), **cfg.task_params)
    space = make_space(cfg.space)
    fit_cfg = FitnessConfig(kind=cfg.fitness, task=task,
                            ppo=standard_ppo(cfg.train_steps, cfg.controllers),
                            classifier=cfg.classifier, physics=cfg.physics, table=cfg.table,
                            classes=cfg.classes,
                            params=fitness_params(cfg.fitness, cfg.fitness_params))
    env = make_env(space, fit_cfg, cfg.num_envs, cfg.horizon, mesh)
    engine = registered(cfg.physics)
    agent = agents.make_agent(cfg.agent, env, agent_cfg, mesh, run, **cfg.agent_params)
    greedy_env = dataclasses.replace(env, num_envs=1)
    p = Pipeline(space, fit_cfg, engine, env.init_fn, env.fitness_fn, env, agent, greedy_env)
    if agent.scores is None:  # a baseline: no policy to roll out
        return p
    return p._replace(greedy_walk=make_greedy_walk(p), greedy_evaluation=make_greedy_evaluation(p))


class Greedy(NamedTuple):
    """A greedy rollout from m0: horizon + 1 bodies, m0 first. The walk (`make_greedy_walk`)
    gives the bodies and actions; their evaluation (`make_greedy_evaluation`, or the confirm
    stage's call, `run.stages.Confirm`) their fitness and controllers."""

    morphs: list  # the bodies (`Morphology`, on the host)
    fitness: list[float] | None  # each body's mean over its fresh controllers; None: not evaluated
    actions: list[str]  # the horizon mutations, named (`action_name`)
    params: list | None  # each body's controllers (trained, for the PPO fitness); where
    # confirmed, best first
    controllers: int | None = None  # the fresh controllers a body's fitness is the mean of;
    # None: the run's K
    confirmed: bool = False  # evaluated in the confirm stage's call, C controllers a body


NO_OP = " (no-op)"


def action_name(space, action: int, before, after) -> str:
    """"node 1: remove", with NO_OP appended where the body did not change (a mutation of the
    root that is a no-op, a move to where a limb already is)."""
    node, mutation = divmod(int(action), space.num_mutations)
    same = space.canonical(before) == space.canonical(after)
    return f"node {node}: {space.mutation_names[mutation]}" + (NO_OP if same else "")


def make_greedy_walk(p: Pipeline):
    """`walk(learner, first, key) -> Greedy`: from m0 (env 0 of `first`, the evaluated start),
    the agent's greedy mutations, with no fitness: an observation is the body and the progress,
    so the horizon's bodies come first and are evaluated side by side afterwards, in one fitness
    call (`make_greedy_evaluation`, or the confirm stage's), not one body a call (one-body calls
    took 32 s for Bad Walker's 5 at 50,000 PPO steps and 117 s for the Constructor's 8 at
    100,000 on an H100, issue 61). The `Greedy` has the bodies, m0 first, and the actions named;
    no fitness yet. Compiled once, reused across calls, on the first device of this process."""
    space, env1, scores = p.space, p.greedy_env, p.agent.scores
    device = jax.local_devices()[0]

    @jax.jit
    def walk(learner, evo, key):
        def body(evo, _):
            obs = env1.observe(evo)
            action = masked_argmax(scores(learner, obs), obs.mask)
            _, child, _ = env1.children(key, evo, action)
            return evo.replace(morph=child, steps=evo.steps + 1), (child, action[0])

        _, (morphs, actions) = jax.lax.scan(body, evo, length=env1.horizon)
        bodies = jax.tree.map(lambda m0, ms: jnp.concatenate([m0, ms[:, 0]]), evo.morph, morphs)
        return bodies, actions

    # one program, not an eager slice per array of the state, each compiled on first use
    env0 = jax.jit(lambda first: jax.tree.map(lambda x: x[:1], first))

    def on_device(learner, first, key):  # env 0 of `first`, with the rest, on `device`, by way
        # of the host: the agent's arrays may span the devices of several processes
        return jax.device_put(to_host((learner, env0(first), key)), device)

    def rollout(learner, first, key) -> Greedy:
        morphs, actions = jax.device_get(walk(*on_device(learner, first, key)))
        bodies = [_at(morphs, i) for i in range(env1.horizon + 1)]
        names = [action_name(space, a, before, after)
                 for a, before, after in zip(actions, bodies, bodies[1:])]
        return Greedy(morphs=bodies, fitness=None, actions=names, params=None)

    def lower(learner, first, key):  # the abstract arguments (`run.stages.Evolve.programs`)
        return walk.lower(*jax.tree.map(_on(device), (learner, jax.eval_shape(env0, first),
                                                      key)))

    rollout.lower = lower  # its program, for compiling ahead (`compile_ahead`)
    return rollout


def make_greedy_evaluation(p: Pipeline):
    """`evaluate(greedy, key) -> Greedy`: the walked bodies of `greedy` (`make_greedy_walk`)
    evaluated under the run's fitness with fresh controllers, in ONE fitness call on the first
    device of this process (`build`). A fresh controller (trained from scratch, as the confirm
    stage's) is the measurement the run's own steps are not: there a child inherits its
    parent's. Where the confirm stage evaluates, these bodies join its call instead
    (`search.confirm.confirm_record`) and this is not called."""
    init_fn, k = p.init_fn, p.fitness.ppo.controllers
    n = p.greedy_env.horizon + 1
    device = jax.local_devices()[0]
    # A program on one device of this process, with no cross-device communication (split over
    # 2 GPUs with Warp it hung, docs/benchmarks.md).
    fitness_fn = make_fitness_fn(p.space, p.fitness, batch_mesh([device]))[1]

    @jax.jit
    def greedy_fitness(bodies, key):
        key_init, key_fit = jax.random.split(key)
        params = jax.vmap(init_fn)(jax.random.split(key_init, n))
        out = fitness_fn(jax.random.split(key_fit, n), bodies, params)
        return out.params, out.fitness

    def evaluate(greedy: Greedy, key) -> Greedy:
        bodies = jax.tree.map(lambda *x: np.stack(x), *greedy.morphs)
        params, fitness = jax.device_get(greedy_fitness(*jax.device_put((bodies, key), device)))
        return greedy._replace(fitness=[float(f) for f in fitness],
                               params=[_at(params, i) for i in range(n)], controllers=k)

    def lower(key):  # the abstract key (`run.stages.Confirm.programs`)
        bodies = jax.eval_shape(lambda: jax.tree.map(
            lambda x: jnp.repeat(jnp.asarray(x)[None], n, 0), p.space.initial()))
        return greedy_fitness.lower(*jax.tree.map(_on(device), (bodies, key)))

    evaluate.lower = lower  # its program, for compiling ahead (`compile_ahead`)
    return evaluate


def _at(tree, i: int):
    """Entry `i` of every array of `tree`."""
    return jax.tree.map(lambda x: x[i], tree)


def _on(device):
    """An array's shape and dtype, placed on `device`: an abstract argument for lowering."""
    return lambda x: jax.ShapeDtypeStruct(
        x.shape, x.dtype, sharding=jax.sharding.SingleDeviceSharding(device))
