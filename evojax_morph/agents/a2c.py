"""Advantage actor-critic over mutations: the source's A3C done the JAX way.

Instead of asynchronous workers, N evolutions unroll in parallel under vmap; every `unroll`
environment steps one synchronous update uses GAE advantages over the stored unroll. One jraph
GNN reads the tree: a per-node policy head gives logits[node, mutation] (a softmax over the
valid actions only) and a pooled head the state value. Acting, mutating, evaluating the batch
of children, storing and learning run in one jitted `lax.scan` per chunk of steps.
"""

from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from brax.training.agents.ppo import losses as ppo_losses
from flax import struct

from evojax_morph.evolution import NEG, EvolutionEnv, EvoState, Observation, track_best
from evojax_morph.gnn import TreeGNN, node_features
from evojax_morph.sharding import jit_replicated


@dataclasses.dataclass(frozen=True)
class A2CConfig:
    """Actor-critic settings; steps are environment steps (one mutation in every parallel env)."""

    hidden: int = 64  # GNN width
    layers: int = 3  # graph convolution rounds
    unroll: int = 4  # environment steps per update
    learning_rate: float = 1e-3
    discount: float = 1.0  # 1: the return of an episode is f_k - f_0
    gae_lambda: float = 0.95
    entropy_cost: float = 0.01
    value_cost: float = 0.5
    reward_scale: float = 1.0  # rewards are multiplied by this before learning
    max_grad_norm: float = 1.0


class ActorCritic(nn.Module):
    """(max_nodes * num_mutations,) logits and a scalar value for one morphology."""

    hidden: int
    layers: int
    num_mutations: int

    @nn.compact
    def __call__(self, m, feats):
        logits, pooled = TreeGNN(self.hidden, self.layers, self.num_mutations)(m, feats)
        value = nn.Dense(1)(nn.relu(nn.Dense(self.hidden)(pooled)))[0]
        return logits.reshape(-1), value


@struct.dataclass
class Unroll:
    """The last `unroll` steps of every env, written in place."""

    obs: Observation  # (T, N, ...)
    action: jax.Array  # (T, N) int32
    reward: jax.Array  # (T, N) scaled
    done: jax.Array  # (T, N) bool: the episode ended at this step


@struct.dataclass
class A2CState:
    params: dict
    opt_state: optax.OptState
    unroll: Unroll
    evo: EvoState  # the parallel evolutions
    first: EvoState  # m0 as reset evaluated it, where ended episodes restart
    key: jax.Array
    step: jax.Array  # () int32: env steps done
    loss: jax.Array  # (): the last update's loss
    best_fitness: jax.Array  # (): best fitness seen in any env
    best_morph: object  # the morphology that had it


def masked_entropy(logits: jax.Array, mask: jax.Array) -> jax.Array:
    """Entropy of the softmax over valid actions only; (..., A) -> (...)."""
    logp = jax.nn.log_softmax(jnp.where(mask, logits, NEG), -1)
    return -jnp.sum(jnp.where(mask, jnp.exp(logp) * logp, 0.0), -1)


def make_agent(env: EvolutionEnv, cfg: A2CConfig, mesh=None):
    """Returns (init(key) -> A2CState, chunk(state, num_steps) -> (state, metrics), logits_fn).

    init and chunk are jitted, their outputs replicated on `mesh` (see `dqn.make_agent`);
    logits_fn(params, obs) -> (N, num_actions): the greedy action is their masked argmax."""
    space = env.space
    net = ActorCritic(cfg.hidden, cfg.layers, space.num_mutations)
    num_kinds, num_sites = len(space.kind_names), len(space.site_names)
    optimizer = optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), optax.adam(cfg.learning_rate))

    def apply(params, obs: Observation):
        """(N, A) logits and (N,) values of a batch of observations."""

        def one(morph, progress):
            return net.apply(params, morph, node_features(morph, progress, num_kinds, num_sites))

        return jax.vmap(one)(obs.morph, obs.progress)

    def init(key: jax.Array) -> A2CState:
        key_net, key_env, key = jax.random.split(key, 3)
        obs, evo = env.reset(key_env)
        single = jax.tree.map(lambda x: x[0], obs)
        params = net.init(key_net, single.morph, node_features(single.morph, single.progress, num_kinds, num_sites))
        t, n = cfg.unroll, env.num_envs
        unroll = Unroll(
            obs=jax.tree.map(lambda x: jnp.zeros((t,) + x.shape, x.dtype), obs),
            action=jnp.zeros((t, n), jnp.int32),
            reward=jnp.zeros((t, n)),
            done=jnp.zeros((t, n), bool),
        )
        best_fitness, best_morph = track_best(evo)
        return A2CState(
            params=params,
            opt_state=optimizer.init(params),
            unroll=unroll,
            evo=evo,
            first=evo,
            key=key,
            step=jnp.zeros((), jnp.int32),
            loss=jnp.zeros(()),
            best_fitness=best_fitness,
            best_morph=best_morph,
        )

    def loss_fn(params, unroll: Unroll, last_obs: Observation):
        flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), unroll.obs)
        logits, values = apply(params, flat)
        t, n = unroll.action.shape
        logits, values = logits.reshape(t, n, -1), values.reshape(t, n)
        _, bootstrap = apply(params, last_obs)
        done = unroll.done.astype(values.dtype)
        targets, advantages = ppo_losses.compute_gae(
            truncation=jnp.zeros_like(done),
            termination=done,
            rewards=unroll.reward,
            values=jax.lax.stop_gradient(values),
            bootstrap_value=jax.lax.stop_gradient(bootstrap),
            lambda_=cfg.gae_lambda,
            discount=cfg.discount,
        )
        logp = jax.nn.log_softmax(jnp.where(unroll.obs.mask, logits, NEG), -1)
        logp_taken = jnp.take_along_axis(logp, unroll.action[..., None], -1)[..., 0]
        policy_loss = -jnp.mean(logp_taken * advantages)
        value_loss = jnp.mean((targets - values) ** 2)
        entropy = jnp.mean(masked_entropy(logits, unroll.obs.mask))
        return policy_loss + cfg.value_cost * value_loss - cfg.entropy_cost * entropy

    def env_step(state: A2CState, _):
        key, key_act, key_env = jax.random.split(state.key, 3)

        # ACT: sample from the softmax over valid actions
        obs = env.observe(state.evo)
        logits, _ = apply(state.params, obs)
        action = jax.random.categorical(key_act, jnp.where(obs.mask, logits, NEG)).astype(jnp.int32)

        # MUTATE AND EVALUATE THE CHILDREN (one batched fitness call)
        _, evo, reward, terminated, truncated, _ = env.step(key_env, state.evo, action)
        best_fitness, best_morph = track_best(evo, state.best_fitness, state.best_morph)
        done = terminated | truncated
        child_fitness = evo.fitness
        evo = env.auto_reset(evo, state.first, done)

        # STORE at this step's place in the unroll
        t = state.step % cfg.unroll
        put = lambda store, x: store.at[t].set(x)
        unroll = Unroll(
            obs=jax.tree.map(put, state.unroll.obs, obs),
            action=state.unroll.action.at[t].set(action),
            reward=state.unroll.reward.at[t].set(reward * cfg.reward_scale),
            done=state.unroll.done.at[t].set(done),
        )

        # UPDATE once the unroll is full, bootstrapping from the state after its last step
        def update(_):
            loss, grads = jax.value_and_grad(loss_fn)(state.params, unroll, env.observe(evo))
            updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
            return optax.apply_updates(state.params, updates), opt_state, loss

        full = t == cfg.unroll - 1
        params, opt_state, loss = jax.lax.cond(
            full, update, lambda _: (state.params, state.opt_state, state.loss), None
        )
        new_state = A2CState(params, opt_state, unroll, evo, state.first, key, state.step + 1, loss,
                             best_fitness, best_morph)
        metrics = {
            "reward": reward,  # (N,)
            "fitness": child_fitness,  # (N,)
            "entropy": jnp.mean(masked_entropy(logits, obs.mask)),  # of the acting policy
            "loss": loss,
            "best_fitness": best_fitness,
        }
        return new_state, metrics

    def chunk(state: A2CState, num_steps: int):
        """`num_steps` env steps in one `lax.scan`; metrics stacked along a leading axis."""
        return jax.lax.scan(env_step, state, length=num_steps)

    init, chunk = jit_replicated(init, chunk, mesh)
    return init, chunk, lambda params, obs: apply(params, obs)[0]

