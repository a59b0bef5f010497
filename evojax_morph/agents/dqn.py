"""Double-DQN over mutations, with a jraph GNN Q-network: one Q-value per (node, mutation).

`DQNConfig(double=False)` (the registered agent "dqn") is plain DQN (Mnih et al. 2015): the
target network both picks and values the next action, the max that Double Q-learning corrects.
`BootstrappedDQNConfig` (the agent "bootdqn") is bootstrapped DQN (Osband et al. 2016, deep
exploration): `heads` Q-value heads on one GNN, each parallel evolution greedy on a head drawn
at its episode's start (no epsilon), each transition training a head with probability
`bootstrap`, so the heads disagree where the data are few and an episode follows one of them
through.

Acts epsilon-greedily over valid actions, stores every transition in a ring buffer inside the
jitted state and takes `updates_per_step` minibatch steps per environment step; the shared loop
(`agents.base`) does the rest. The network (`q_network`) and the replay learning
(`replay_policy`) are shared with QR-DQN (`agents.qrdqn`), which changes only the outputs per
action and the loss.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import optax
from flax import struct

from evojax_morph.agents.base import Policy, RunOptions, Transition
from evojax_morph.agents.gnn import TreeGNN, node_features
from evojax_morph.mdp import EvolutionEnv, Observation, masked_argmax, random_valid_actions


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
    double: bool = True  # Double Q-learning's target; False: plain DQN's max over the target net
    heads: int = 1  # Q-value heads (bootstrapped DQN: more than 1)
    bootstrap: float = 0.5  # heads > 1: the chance a transition trains a head

    @classmethod
    def for_run(cls, env: EvolutionEnv, run: RunOptions) -> DQNConfig:
        """A run's settings: epsilon anneals over its explore steps, minibatches of 32; the
        rewards scaled as `env`'s are for a run's agent."""
        return cls(hidden=run.hidden, reward_scale=env.reward_scale,
                   epsilon_steps=run.explore_steps, learning_starts=run.learning_starts,
                   batch_size=32)


@dataclasses.dataclass(frozen=True)
class PlainDQNConfig(DQNConfig):
    """Plain DQN's settings: `DQNConfig` with DQN's own target (the agent "dqn")."""

    double: bool = False


@dataclasses.dataclass(frozen=True)
class BootstrappedDQNConfig(DQNConfig):
    """Bootstrapped DQN's settings (the agent "bootdqn"): 10 heads, each transition in about
    half of their data sets, greedy on an episode's head without epsilon."""

    heads: int = 10
    epsilon_start: float = 0.0
    epsilon_end: float = 0.0

    @classmethod
    def for_run(cls, env: EvolutionEnv, run: RunOptions) -> BootstrappedDQNConfig:
        """`DQNConfig.for_run`'s settings, without its epsilon (the heads explore)."""
        return dataclasses.replace(super().for_run(env, run), epsilon_start=0.0,
                                   epsilon_end=0.0)


@struct.dataclass
class Buffer:
    """A ring buffer of transitions inside the jitted state."""

    obs: Observation  # (C, ...)
    action: jax.Array  # (C,) int32
    reward: jax.Array  # (C,)
    next_obs: Observation  # (C, ...)
    terminal: jax.Array  # (C,) bool
    heads: jax.Array  # (C, H) bool: the heads each transition trains
    pos: jax.Array  # () int32: next slot to write
    size: jax.Array  # () int32: slots filled


@struct.dataclass
class DQNLearner:
    params: dict
    target_params: dict
    opt_state: optax.OptState
    buffer: Buffer
    head: jax.Array  # (N,) int32: the head each parallel evolution follows this episode


def double_q_target(reward, terminal, discount, q_next_online, q_next_target, next_mask):
    """r + gamma (1 - terminal) Q_target(s', argmax over valid a' of Q_online(s', a')).

    Args:
      reward, terminal: (B,) float.
      q_next_online, q_next_target: (B, A) Q-values of s' by the online and target networks.
      next_mask: (B, A) bool, the valid actions in s'.
    Returns:
      (B,) targets.
    """
    best = masked_argmax(q_next_online, next_mask)
    value = jnp.take_along_axis(q_next_target, best[..., None], -1)[..., 0]
    value = jnp.where(next_mask.any(-1), value, 0.0)  # no valid action: nothing to bootstrap
    return reward + discount * (1.0 - terminal) * value


def epsilon(cfg: DQNConfig, step) -> jax.Array:
    frac = jnp.clip(step / max(cfg.epsilon_steps, 1), 0.0, 1.0)
    return cfg.epsilon_start + frac * (cfg.epsilon_end - cfg.epsilon_start)


def q_network(space, cfg: DQNConfig, outputs: int = 1):
    """The GNN over the tree with `outputs` values per action (1: a Q-value; QR-DQN: its
    quantiles), read off a shared per-node head.

    Returns:
      (init, apply): init(key, obs) -> params, from an (N, ...) observation;
      apply(params, obs) -> (N, num_actions, outputs), action `node * num_mutations + mutation`.
    """
    net = TreeGNN(hidden=cfg.hidden, layers=cfg.layers, out_size=space.num_mutations * outputs)
    num_kinds, num_sites = len(space.kind_names), len(space.site_names)

    def one(params, morph, progress):
        feats = node_features(morph, progress, num_kinds, num_sites)
        out, _ = net.apply(params, morph, feats)
        return out.reshape(-1, outputs)  # (max_nodes * num_mutations, outputs)

    def apply(params, obs: Observation) -> jax.Array:
        return jax.vmap(one, (None, 0, 0))(params, obs.morph, obs.progress)

    def init(key: jax.Array, obs: Observation) -> dict:
        single = jax.tree.map(lambda x: x[0], obs)
        return net.init(key, single.morph, node_features(single.morph, single.progress,
                                                         num_kinds, num_sites))

    return init, apply


def empty_buffer(cfg: DQNConfig, obs: Observation) -> Buffer:
    """A replay buffer of `cfg.buffer_size` transitions shaped as one of `obs`'s rows."""
    cap = cfg.buffer_size
    empty = lambda x: jnp.zeros((cap,) + x.shape[1:], x.dtype)  # noqa: E731
    return Buffer(
        obs=jax.tree.map(empty, obs),
        action=jnp.zeros(cap, jnp.int32),
        reward=jnp.zeros(cap),
        next_obs=jax.tree.map(empty, obs),
        terminal=jnp.zeros(cap, bool),
        heads=jnp.zeros((cap, cfg.heads), bool),
        pos=jnp.zeros((), jnp.int32),
        size=jnp.zeros((), jnp.int32),
    )


def store(cfg: DQNConfig, buf: Buffer, tr: Transition, trains: jax.Array) -> Buffer:
    """`buf` with the N transitions of `tr` (their rewards scaled, the heads each trains)
    written over its oldest (a ring)."""
    n = tr.action.shape[0]
    idx = (buf.pos + jnp.arange(n)) % cfg.buffer_size
    put = lambda old, x: old.at[idx].set(x)  # noqa: E731
    return Buffer(
        obs=jax.tree.map(put, buf.obs, tr.obs),
        action=buf.action.at[idx].set(tr.action),
        reward=buf.reward.at[idx].set(tr.reward * cfg.reward_scale),
        next_obs=jax.tree.map(put, buf.next_obs, tr.next_obs),
        terminal=buf.terminal.at[idx].set(tr.terminated),
        heads=buf.heads.at[idx].set(trains),
        pos=(buf.pos + n) % cfg.buffer_size,
        size=jnp.minimum(buf.size + n, cfg.buffer_size),
    )


def replay_policy(env: EvolutionEnv, cfg: DQNConfig, init_net, values_fn, loss_fn) -> Policy:
    """Acting and learning of a Q-learning agent with a target network and a replay buffer.

    Args:
      env: the environment (its observations size the buffer).
      cfg: the DQN settings (a `DQNConfig` or a subclass).
      init_net: init_net(key, obs) -> the network's params (`q_network`).
      values_fn: values_fn(params, obs) -> (N, num_actions, cfg.heads) action values:
        acting is epsilon-greedy on the masked argmax of an evolution's head, and their mean
        over heads is the agent's scores.
      loss_fn: loss_fn(params, target_params, batch) -> () loss of a minibatch
        (obs, action, reward, next_obs, terminal, heads), each with a leading (batch_size,)
        axis (heads: (batch_size, cfg.heads) bool, the heads a transition trains).
    """
    optimizer = optax.chain(
        optax.clip_by_global_norm(cfg.max_grad_norm), optax.adam(cfg.learning_rate)
    )

    def init(keys: jax.Array, obs: Observation) -> DQNLearner:
        params = init_net(keys[0], obs)
        head = jax.random.randint(jax.random.fold_in(keys[0], 1), (obs.mask.shape[0],), 0,
                                  cfg.heads)
        return DQNLearner(params, params, optimizer.init(params), empty_buffer(cfg, obs), head)

    def act(learner: DQNLearner, keys: jax.Array, obs: Observation, step):
        """Epsilon-greedy over valid actions only, greedy on each evolution's head."""
        key_eps, key_rand = keys
        values = jnp.take_along_axis(values_fn(learner.params, obs),
                                     learner.head[:, None, None], -1)[..., 0]
        greedy = masked_argmax(values, obs.mask)
        uniform = random_valid_actions(key_rand, obs.mask)
        explore = jax.random.uniform(key_eps, (obs.mask.shape[0],)) < epsilon(cfg, step)
        action = jnp.where(explore, uniform, greedy).astype(jnp.int32)
        return action, {"epsilon": epsilon(cfg, step)}

    def learn(learner: DQNLearner, keys: jax.Array, tr: Transition, step):
        key, head = keys[0], learner.head
        if cfg.heads > 1:  # a new episode's head; the heads each transition trains
            key, key_head, key_boot = jax.random.split(key, 3)
            head = jnp.where(tr.done, jax.random.randint(key_head, head.shape, 0, cfg.heads),
                             head)
            trains = jax.random.bernoulli(key_boot, cfg.bootstrap, (len(head), cfg.heads))
        else:
            trains = jnp.ones((len(head), 1), bool)
        buf = store(cfg, learner.buffer, tr, trains)  # STORE

        # UPDATE: updates_per_step minibatches, once enough transitions are stored
        def update(carry, key):
            params, opt_state = carry
            idx = jax.random.randint(key, (cfg.batch_size,), 0, jnp.maximum(buf.size, 1))
            batch = jax.tree.map(lambda x: x[idx], (buf.obs, buf.action, buf.reward,
                                                    buf.next_obs, buf.terminal, buf.heads))
            loss, grads = jax.value_and_grad(loss_fn)(params, learner.target_params, batch)
            updates, new_opt = optimizer.update(grads, opt_state, params)
            ready = buf.size >= cfg.learning_starts
            keep = lambda new, old: jnp.where(ready, new, old)  # noqa: E731
            params = jax.tree.map(keep, optax.apply_updates(params, updates), params)
            return (params, jax.tree.map(keep, new_opt, opt_state)), loss

        (params, opt_state), losses = jax.lax.scan(
            update, (learner.params, learner.opt_state),
            jax.random.split(key, cfg.updates_per_step),
        )
        copy = (step + 1) % cfg.target_period == 0
        target = jax.tree.map(lambda t, p: jnp.where(copy, p, t), learner.target_params, params)
        return DQNLearner(params, target, opt_state, buf, head), {"loss": losses.mean()}

    return Policy(keys=(1, 2, 1), init=init, act=act, learn=learn,
                  scores=lambda learner, obs: values_fn(learner.params, obs).mean(-1))


def make_policy(env: EvolutionEnv, cfg: DQNConfig) -> Policy:
    """(Double-, bootstrapped) DQN's acting and learning; scores are the Q-values (their mean
    over the heads)."""
    init_net, q_fn = q_network(env.space, cfg, cfg.heads)  # (N, num_actions, heads)

    def loss_fn(params, target_params, batch):
        obs, action, reward, next_obs, terminal, trains = batch
        q = jnp.moveaxis(q_fn(params, obs), -1, 0)  # (H, B, A)
        q_taken = jnp.take_along_axis(q, action[None, :, None], -1)[..., 0]  # (H, B)
        q_next = jnp.moveaxis(q_fn(target_params, next_obs), -1, 0)
        q_pick = jnp.moveaxis(q_fn(params, next_obs), -1, 0) if cfg.double else q_next
        target = jax.vmap(double_q_target, (None, None, None, 0, 0, None))(
            reward, terminal.astype(q.dtype), cfg.discount, q_pick, q_next, next_obs.mask)
        loss = optax.huber_loss(q_taken, jax.lax.stop_gradient(target))  # (H, B)
        return jnp.sum(loss * trains.T) / jnp.maximum(jnp.sum(trains), 1)

    return replay_policy(env, cfg, init_net, q_fn, loss_fn)
