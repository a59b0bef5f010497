"""A whole run assembled from its config: space -> fitness -> evolution env -> agent.

`build(cfg)` is what the `run` command, the experiments and the tests use; the greedy rollout
reads a trained agent's choices from m0.
"""

from __future__ import annotations

import dataclasses

import jax

from evojax_morph import agents
from evojax_morph.agents.dqn import masked_argmax
from evojax_morph.evolution import EvolutionEnv
from evojax_morph.fitness import make_fitness_fn
from evojax_morph.fitnesses import FitnessConfig, get_fitness
from evojax_morph.ppo import PPOConfig
from evojax_morph.sharding import to_host
from evojax_morph.spaces import make_space


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything that defines a run; saved as config.json, reloaded by --resume."""

    space: str = "bad_walker"
    fitness: str = "ppo"  # a registered fitness kind: ppo | predefined | tame
    classifier: str = ""  # tame: directory of the trained classifier
    agent: str = "ddqn"
    steps: int = 40  # environment steps; each mutates every parallel evolution once
    seed: int = 0
    num_envs: int = 4  # parallel evolutions, each step's fitness batch
    horizon: int = 0  # mutations per episode; 0 picks the space's default
    train_steps: int = 10_000  # PPO control steps per fitness evaluation
    hidden: int = 64  # GNN width
    explore_steps: int = 20  # environment steps over which epsilon anneals from 1 to 0.05
    learning_starts: int = 32  # transitions stored before the Q-network learns
    chunk: int = 5  # environment steps per jitted call
    checkpoint_every: int = 1  # chunks between checkpoints

    def resolved_horizon(self) -> int:
        if self.horizon:
            return self.horizon
        return make_space(self.space).max_nodes - 1 if self.space == "constructor" else 4


def build(cfg: RunConfig):
    """(space, env, greedy_env, init, chunk, scores_fn): the run's parts (see `agents`)."""
    space = make_space(cfg.space)
    fit_cfg = FitnessConfig(
        kind=cfg.fitness,
        ppo=PPOConfig(train_steps=cfg.train_steps, num_envs=16, unroll_length=20),
        classifier=cfg.classifier,
    )
    init_fn, fitness_fn = make_fitness_fn(space, fit_cfg)
    horizon = cfg.resolved_horizon()
    env = EvolutionEnv(space, fitness_fn, init_fn, horizon=horizon, num_envs=cfg.num_envs)
    scale = get_fitness(cfg.fitness).scale(space)
    extra = {
        "ddqn": {"epsilon_steps": cfg.explore_steps, "learning_starts": cfg.learning_starts,
                 "batch_size": 32},
        "a2c": {"unroll": horizon},  # one update per episode of every parallel evolution
    }.get(cfg.agent, {})
    init, chunk, scores_fn = agents.make_agent(cfg.agent, env, cfg.hidden, 1.0 / scale, **extra)
    greedy_env = dataclasses.replace(env, num_envs=1)
    return space, env, greedy_env, init, chunk, scores_fn


def make_greedy_rollout(space, env1: EvolutionEnv, scores_fn):
    """`rollout(params, first, key)`: from m0 (as `first`, the evaluated start of env 0), the
    agent's greedy mutations, with each body's fitness. Compiled once, reused across calls."""

    @jax.jit
    def run(params, first, key):
        evo = jax.tree.map(lambda x: x[:1], first)

        def body(evo, key):
            obs = env1.observe(evo)
            action = masked_argmax(scores_fn(params, obs), obs.mask)
            _, evo, *_ = env1.step(key, evo, action)
            return evo, (evo.morph, evo.fitness[0], action[0])

        _, (morphs, fitness, actions) = jax.lax.scan(body, evo, jax.random.split(key, env1.horizon))
        return morphs, fitness, actions

    def rollout(params, first, key):
        morphs, fitness, actions = to_host(run(params, first, key))
        first_morph, first_fitness = to_host((first.morph, first.fitness))
        m0 = jax.tree.map(lambda x: x[0], first_morph)
        seq = [m0] + [jax.tree.map(lambda x, i=i: x[i, 0], morphs) for i in range(env1.horizon)]
        nm = space.num_mutations
        names = [f"node {a // nm}: {space.mutation_names[a % nm]}" for a in actions]
        return seq, [float(first_fitness[0])] + [float(f) for f in fitness], names

    return rollout
