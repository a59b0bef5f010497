"""Double-DQN over mutations, with a jraph GNN Q-network: one Q-value per (node, mutation).

Act, mutate, evaluate the batch of children, store and update all run in one jitted function,
`lax.scan`ned over a chunk of environment steps; Python only logs and checkpoints between chunks.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import optax
from flax import struct

from evojax_morph.evolution import (
    NEG,
    EvolutionEnv,
    EvoState,
    Observation,
    random_valid_actions,
    track_best,
)
from evojax_morph.gnn import TreeGNN, node_features
from evojax_morph.sharding import jit_replicated


@dataclasses.dataclass(frozen=True)
class DQNConfig:
    """Double-DQN settings; steps are environment steps (one mutation in every parallel env)."""

    hidden: int = 64  # GNN width (the source compared 20 and 100)
    layers: int = 3  # graph convolution rounds
    buffer_size: int = 20_000  # transitions
    batch_size: int = 64
    learning_rate: float = 1e-3
    discount: float = 0.99
    target_period: int = 10  # env steps between copies to the target network
    updates_per_step: int = 4
    learning_starts: int = 64  # transitions stored before learning starts
    epsilon_start: float = 1.0
    epsilon_end: float = 0.05
    epsilon_steps: int = 100  # env steps of linear annealing
    reward_scale: float = 1.0  # rewards are multiplied by this before learning
    max_grad_norm: float = 10.0


@struct.dataclass
class Buffer:
    """A ring buffer of transitions inside the jitted state."""

    obs: Observation  # (C, ...)
    action: jax.Array  # (C,) int32
    reward: jax.Array  # (C,)
    next_obs: Observation  # (C, ...)
    terminal: jax.Array  # (C,) bool
    pos: jax.Array  # () int32: next slot to write
    size: jax.Array  # () int32: slots filled


@struct.dataclass
class DQNState:
    params: dict
    target_params: dict
    opt_state: optax.OptState
    buffer: Buffer
    evo: EvoState  # the parallel evolutions
    first: EvoState  # m0 as reset evaluated it, where ended episodes restart
    key: jax.Array
    step: jax.Array  # () int32: env steps done
    best_fitness: jax.Array  # (): best fitness seen in any env
    best_morph: object  # the morphology that had it


def masked_argmax(q: jax.Array, mask: jax.Array) -> jax.Array:
    return jnp.argmax(jnp.where(mask, q, NEG), axis=-1)


def double_q_target(reward, terminal, discount, q_next_online, q_next_target, next_mask):
    """r + gamma (1 - terminal) Q_target(s', argmax over valid a' of Q_online(s', a'))."""
    best = masked_argmax(q_next_online, next_mask)
    value = jnp.take_along_axis(q_next_target, best[..., None], -1)[..., 0]
    value = jnp.where(next_mask.any(-1), value, 0.0)  # no valid action: nothing to bootstrap
    return reward + discount * (1.0 - terminal) * value


def epsilon(cfg: DQNConfig, step) -> jax.Array:
    frac = jnp.clip(step / max(cfg.epsilon_steps, 1), 0.0, 1.0)
    return cfg.epsilon_start + frac * (cfg.epsilon_end - cfg.epsilon_start)


def make_agent(env: EvolutionEnv, cfg: DQNConfig, mesh=None):
    """Returns (init(key) -> DQNState, chunk(state, num_steps) -> (state, metrics), q_fn).

    init and chunk are jitted with their outputs replicated on every device of `mesh` (default:
    all; the fitness inside splits its batch across them): the agent is small, and a state
    whose placement never changes compiles once.
    """
    space = env.space
    net = TreeGNN(hidden=cfg.hidden, layers=cfg.layers, out_size=space.num_mutations)
    num_kinds, num_sites = len(space.kind_names), len(space.site_names)
    optimizer = optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), optax.adam(cfg.learning_rate))

    def q_one(params, morph, progress):
        feats = node_features(morph, progress, num_kinds, num_sites)
        q, _ = net.apply(params, morph, feats)
        return q.reshape(-1)  # (max_nodes * num_mutations,)

    def q_fn(params, obs: Observation) -> jax.Array:
        """(N, num_actions) Q-values of a batch of observations."""
        return jax.vmap(q_one, (None, 0, 0))(params, obs.morph, obs.progress)

    def init(key: jax.Array) -> DQNState:
        key_net, key_env, key = jax.random.split(key, 3)
        obs, evo = env.reset(key_env)
        single = jax.tree.map(lambda x: x[0], obs)
        params = net.init(key_net, single.morph, node_features(single.morph, single.progress, num_kinds, num_sites))
        cap = cfg.buffer_size
        empty = lambda x: jnp.zeros((cap,) + x.shape[1:], x.dtype)
        buffer = Buffer(
            obs=jax.tree.map(empty, obs),
            action=jnp.zeros(cap, jnp.int32),
            reward=jnp.zeros(cap),
            next_obs=jax.tree.map(empty, obs),
            terminal=jnp.zeros(cap, bool),
            pos=jnp.zeros((), jnp.int32),
            size=jnp.zeros((), jnp.int32),
        )
        best_fitness, best_morph = track_best(evo)
        return DQNState(
            params=params,
            target_params=params,
            opt_state=optimizer.init(params),
            buffer=buffer,
            evo=evo,
            first=evo,
            key=key,
            step=jnp.zeros((), jnp.int32),
            best_fitness=best_fitness,
            best_morph=best_morph,
        )

    def loss_fn(params, target_params, batch):
        obs, action, reward, next_obs, terminal = batch
        q = q_fn(params, obs)
        q_taken = jnp.take_along_axis(q, action[:, None], -1)[:, 0]
        target = double_q_target(
            reward,
            terminal.astype(q.dtype),
            cfg.discount,
            q_fn(params, next_obs),
            q_fn(target_params, next_obs),
            next_obs.mask,
        )
        return jnp.mean(optax.huber_loss(q_taken, jax.lax.stop_gradient(target)))

    def env_step(state: DQNState, _):
        key, key_eps, key_rand, key_env, key_upd = jax.random.split(state.key, 5)
        n = env.num_envs

        # ACT: epsilon-greedy over valid actions only
        obs = env.observe(state.evo)
        greedy = masked_argmax(q_fn(state.params, obs), obs.mask)
        uniform = random_valid_actions(key_rand, obs.mask)
        explore = jax.random.uniform(key_eps, (n,)) < epsilon(cfg, state.step)
        action = jnp.where(explore, uniform, greedy).astype(jnp.int32)

        # MUTATE AND EVALUATE THE CHILDREN (one batched fitness call)
        next_obs, evo, reward, terminated, truncated, _ = env.step(key_env, state.evo, action)
        best_fitness, best_morph = track_best(evo, state.best_fitness, state.best_morph)

        # STORE
        buf = state.buffer
        idx = (buf.pos + jnp.arange(n)) % cfg.buffer_size
        put = lambda store, x: store.at[idx].set(x)
        buf = Buffer(
            obs=jax.tree.map(put, buf.obs, obs),
            action=buf.action.at[idx].set(action),
            reward=buf.reward.at[idx].set(reward * cfg.reward_scale),
            next_obs=jax.tree.map(put, buf.next_obs, next_obs),
            terminal=buf.terminal.at[idx].set(terminated),
            pos=(buf.pos + n) % cfg.buffer_size,
            size=jnp.minimum(buf.size + n, cfg.buffer_size),
        )
        child_fitness = evo.fitness
        evo = env.auto_reset(evo, state.first, terminated | truncated)

        # UPDATE: updates_per_step minibatches, once enough transitions are stored
        def update(carry, key):
            params, opt_state = carry
            idx = jax.random.randint(key, (cfg.batch_size,), 0, jnp.maximum(buf.size, 1))
            batch = jax.tree.map(lambda x: x[idx], (buf.obs, buf.action, buf.reward, buf.next_obs, buf.terminal))
            loss, grads = jax.value_and_grad(loss_fn)(params, state.target_params, batch)
            updates, new_opt = optimizer.update(grads, opt_state, params)
            ready = buf.size >= cfg.learning_starts
            keep = lambda new, old: jnp.where(ready, new, old)
            new = (jax.tree.map(keep, optax.apply_updates(params, updates), params), jax.tree.map(keep, new_opt, opt_state))
            return new, loss

        (params, opt_state), losses = jax.lax.scan(
            update, (state.params, state.opt_state), jax.random.split(key_upd, cfg.updates_per_step)
        )
        step = state.step + 1
        target = jax.tree.map(
            lambda t, p: jnp.where(step % cfg.target_period == 0, p, t), state.target_params, params
        )
        new_state = DQNState(params, target, opt_state, buf, evo, state.first, key, step, best_fitness, best_morph)
        metrics = {
            "reward": reward,  # (N,)
            "fitness": child_fitness,  # (N,)
            "epsilon": epsilon(cfg, state.step),
            "loss": losses.mean(),
            "best_fitness": best_fitness,
        }
        return new_state, metrics

    def chunk(state: DQNState, num_steps: int):
        """`num_steps` env steps in one `lax.scan`; metrics stacked along a leading axis."""
        return jax.lax.scan(env_step, state, length=num_steps)

    init, chunk = jit_replicated(init, chunk, mesh)
    return init, chunk, q_fn

