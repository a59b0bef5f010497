"""Advantage actor-critic over mutations: the source's A3C done the JAX way.

Instead of asynchronous workers, N evolutions unroll in parallel under vmap; every `unroll`
environment steps one synchronous update uses GAE advantages over the stored unroll,
bootstrapped with the value of the state after it. The default, `unroll` 1, updates after every
step from its N transitions (advantage r + V(s') - V(s)), within episodes as A3C's workers
update; one update per episode (`unroll` = horizon) left the agent 80 updates in Figure 4,
too few to learn Bad Walker. One jraph GNN reads the tree: a per-node policy head gives
logits[node, mutation] (a softmax over the valid actions only) and a pooled head the state
value. The shared loop (`agents.base`) acts, mutates, evaluates the children and calls `learn`
in one jitted `lax.scan` per chunk of steps.
"""

from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from brax.training.agents.ppo import losses as ppo_losses
from flax import struct

from evojax_morph.agents.base import Policy, RunOptions, Transition
from evojax_morph.agents.gnn import TreeGNN, node_features
from evojax_morph.mdp import NEG, EvolutionEnv, Observation


@dataclasses.dataclass(frozen=True)
class A2CConfig:
    """Actor-critic settings; steps are environment steps (one mutation in every parallel env)."""

    hidden: int = 64  # GNN width
    layers: int = 3  # graph convolution rounds
    unroll: int = 1  # environment steps per update; 1: an update every step
    learning_rate: float = 1e-3
    discount: float = 1.0  # 1: the return of an episode is f_k - f_0
    gae_lambda: float = 0.95
    # With an update every step, 0.01 to 0.02 let Bad Walker's policy drop the long foot's
    # removal along with the short feet's (the GNN's "remove" outputs start alike) before it
    # tells them apart, and settle for no-ops (docs/results.md, Figure 4).
    entropy_cost: float = 0.06
    value_cost: float = 0.5
    reward_scale: float = 1.0  # rewards are multiplied by this before learning
    max_grad_norm: float = 1.0

    @classmethod
    def for_run(cls, env: EvolutionEnv, run: RunOptions) -> A2CConfig:
        """A run's settings: one update per environment step (`unroll` 1); the rewards scaled
        as `env`'s are for a run's agent."""
        return cls(hidden=run.hidden, reward_scale=env.reward_scale)


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
class A2CLearner:
    params: dict
    opt_state: optax.OptState
    unroll: Unroll
    loss: jax.Array  # (): the last update's loss
    value_loss: jax.Array  # (): its value term, (target - value)^2 before value_cost


def masked_entropy(logits: jax.Array, mask: jax.Array) -> jax.Array:
    """Entropy of the softmax over valid actions only; (..., A) -> (...)."""
    logp = jax.nn.log_softmax(jnp.where(mask, logits, NEG), -1)
    return -jnp.sum(jnp.where(mask, jnp.exp(logp) * logp, 0.0), -1)


def make_loss_fn(apply, cfg: A2CConfig):
    """`loss_fn(params, unroll, last_obs) -> (loss, value_loss)`, with GAE advantages over the
    unroll bootstrapped from `last_obs`; `apply(params, obs)` gives (N, A) logits and (N,)
    values."""

    def loss_fn(params, unroll: Unroll, last_obs: Observation):
        """The actor-critic loss of a full unroll and its value term (before value_cost)."""
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
        loss = policy_loss + cfg.value_cost * value_loss - cfg.entropy_cost * entropy
        return loss, value_loss

    return loss_fn


def make_policy(env: EvolutionEnv, cfg: A2CConfig) -> Policy:
    """The actor-critic's acting and learning; scores are the policy logits."""
    space = env.space
    net = ActorCritic(cfg.hidden, cfg.layers, space.num_mutations)
    num_kinds, num_sites = len(space.kind_names), len(space.site_names)
    optimizer = optax.chain(
        optax.clip_by_global_norm(cfg.max_grad_norm), optax.adam(cfg.learning_rate)
    )

    def apply(params, obs: Observation):
        """(N, A) logits and (N,) values of a batch of observations."""

        def one(morph, progress):
            return net.apply(params, morph, node_features(morph, progress, num_kinds, num_sites))

        return jax.vmap(one)(obs.morph, obs.progress)

    loss_fn = make_loss_fn(apply, cfg)

    def init(keys: jax.Array, obs: Observation) -> A2CLearner:
        single = jax.tree.map(lambda x: x[0], obs)
        feats = node_features(single.morph, single.progress, num_kinds, num_sites)
        params = net.init(keys[0], single.morph, feats)
        t, n = cfg.unroll, env.num_envs
        unroll = Unroll(
            obs=jax.tree.map(lambda x: jnp.zeros((t,) + x.shape, x.dtype), obs),
            action=jnp.zeros((t, n), jnp.int32),
            reward=jnp.zeros((t, n)),
            done=jnp.zeros((t, n), bool),
        )
        return A2CLearner(params, optimizer.init(params), unroll, jnp.zeros(()), jnp.zeros(()))

    def act(learner: A2CLearner, keys: jax.Array, obs: Observation, step):
        """A sample of the softmax over valid actions."""
        logits, _ = apply(learner.params, obs)
        action = jax.random.categorical(keys[0], jnp.where(obs.mask, logits, NEG))
        return action.astype(jnp.int32), {"entropy": jnp.mean(masked_entropy(logits, obs.mask))}

    def learn(learner: A2CLearner, keys: jax.Array, tr: Transition, step):
        del keys
        # STORE at this step's place in the unroll
        t = step % cfg.unroll
        put = lambda store, x: store.at[t].set(x)  # noqa: E731
        unroll = Unroll(
            obs=jax.tree.map(put, learner.unroll.obs, tr.obs),
            action=put(learner.unroll.action, tr.action),
            reward=put(learner.unroll.reward, tr.reward * cfg.reward_scale),
            done=put(learner.unroll.done, tr.done),
        )

        # UPDATE once the unroll is full, bootstrapping from the state after its last step (an
        # ended episode's bootstrap is masked out, so the state before the restart will do)
        def update(_):
            (loss, value_loss), grads = jax.value_and_grad(loss_fn, has_aux=True)(
                learner.params, unroll, tr.next_obs
            )
            updates, opt_state = optimizer.update(grads, learner.opt_state, learner.params)
            return optax.apply_updates(learner.params, updates), opt_state, loss, value_loss

        keep = lambda _: (learner.params, learner.opt_state, learner.loss, learner.value_loss)  # noqa: E731
        params, opt_state, loss, value_loss = jax.lax.cond(
            t == cfg.unroll - 1, update, keep, None
        )
        learner = A2CLearner(params, opt_state, unroll, loss, value_loss)
        return learner, {"loss": loss, "value_loss": value_loss}

    return Policy(keys=(1, 1, 0), init=init, act=act, learn=learn,
                  scores=lambda learner, obs: apply(learner.params, obs)[0])
