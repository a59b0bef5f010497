"""The inner PPO's settings and networks: `PPOConfig`, a controller's parameters, the masked
log-probability and entropy, the clipped loss.

brax's PPO networks (`make_networks`) act on the padded template's whole action vector; the
log-probability and entropy here sum over the motors a body has only (brax's sum over every
action dimension). `evojax_morph.ppo` trains them and re-exports these names.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
from brax.training import distribution
from brax.training.acme import running_statistics
from brax.training.agents.ppo import networks as brax_networks

from evojax_morph.tasks import Locomotion


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """Inner PPO settings; budgets are per morphology.

    Attributes:
      train_steps: control steps of training, over all its worlds
      worlds_per_controller: parallel worlds each controller trains in (brax's `num_envs`)
      unroll_length: control steps per world between updates
      num_minibatches: minibatches an update's batch (worlds_per_controller x unroll_length)
        is split into
      update_epochs: passes over each update's batch
      learning_rate: Adam's step size
      discount: the return's discount factor (gamma)
      gae_lambda: the lambda of generalised advantage estimation
      clip_eps: PPO's clipping of the probability ratio
      entropy_cost: the weight of the policy's entropy bonus
      vf_coef: the weight of the value loss
      max_grad_norm: gradients clipped to this global norm
      reward_scaling: rewards multiplied by this before learning
      normalize_observations: observations normalised by running statistics (`Params.normalizer`)
      policy_hidden: the policy network's hidden layer widths
      value_hidden: the value network's hidden layer widths
      eval_episodes: deterministic episodes of episode_length after training
      controllers: K independent controllers per body; the fitness is their mean
    """

    train_steps: int = 100_000
    worlds_per_controller: int = 32
    unroll_length: int = 20
    num_minibatches: int = 4
    update_epochs: int = 8
    learning_rate: float = 1e-3
    discount: float = 0.97
    gae_lambda: float = 0.95
    clip_eps: float = 0.3
    entropy_cost: float = 1e-2
    vf_coef: float = 0.5
    max_grad_norm: float = 1.0
    reward_scaling: float = 1.0
    normalize_observations: bool = True
    policy_hidden: tuple[int, ...] = (32, 32)
    value_hidden: tuple[int, ...] = (64, 64)
    eval_episodes: int = 4
    controllers: int = 1

    @property
    def num_updates(self) -> int:
        return max(1, self.train_steps // (self.worlds_per_controller * self.unroll_length))

    def validate(self) -> None:
        batch = self.worlds_per_controller * self.unroll_length
        if self.train_steps < 0 or self.worlds_per_controller < 1 or self.unroll_length < 1:
            raise ValueError("train_steps must be >= 0, worlds_per_controller and unroll_length "
                             ">= 1")
        if batch % self.num_minibatches:
            raise ValueError(
                f"worlds_per_controller x unroll_length ({batch}) must divide into "
                f"{self.num_minibatches} minibatches"
            )
        if self.eval_episodes < 1 or self.controllers < 1:
            raise ValueError("eval_episodes and controllers must be at least 1")


class Params(NamedTuple):
    """A controller: what a child inherits from its parent.

    Attributes:
      normalizer: the running mean and variance the observations are normalised by (brax's
        `running_statistics`)
      policy: the policy network's weights (flax)
      value: the value network's weights (flax)
    """

    normalizer: running_statistics.RunningStatisticsState
    policy: dict
    value: dict


class Transition(NamedTuple):
    """One learner's trajectory of T steps in E worlds: what its PPO update learns from."""

    obs: jax.Array  # (T, E, obs_size)
    raw_action: jax.Array  # (T, E, A) pre-tanh
    log_prob: jax.Array  # (T, E)
    reward: jax.Array  # (T, E)
    terminated: jax.Array  # (T, E) float
    truncated: jax.Array  # (T, E) float
    diverged: jax.Array  # (T, E) bool


def masked_log_prob(dist: distribution.NormalTanhDistribution, logits, raw_action, mask):
    """log pi(a) summed over the active action dimensions only.

    Args:
      dist: brax's tanh-normal action distribution.
      logits: (..., 2A) policy output.
      raw_action: (..., A) pre-tanh action.
      mask: (A,) bool, the motors the body has.
    Returns:
      (...,) log-probability of tanh(raw_action).
    """
    per_dim = dist.create_dist(logits).log_prob(raw_action)
    per_dim -= distribution.TanhBijector().forward_log_det_jacobian(raw_action)
    return jnp.sum(jnp.where(mask, per_dim, 0.0), axis=-1)


def masked_entropy(dist: distribution.NormalTanhDistribution, logits, key, mask):
    """Entropy of the tanh-normal over active dimensions, estimated with one sample as brax does."""
    normal = dist.create_dist(logits)
    per_dim = normal.entropy() + distribution.TanhBijector().forward_log_det_jacobian(
        normal.sample(key)
    )
    return jnp.sum(jnp.where(mask, per_dim, 0.0), axis=-1)


def make_networks(env: Locomotion, cfg: PPOConfig):
    """brax's PPO networks for the task's observations and actions, as `cfg` sizes them."""
    return brax_networks.make_ppo_networks(
        env.obs_size,
        env.action_size,
        preprocess_observations_fn=running_statistics.normalize
        if cfg.normalize_observations
        else (lambda obs, _: obs),
        policy_hidden_layer_sizes=cfg.policy_hidden,
        value_hidden_layer_sizes=cfg.value_hidden,
    )


def make_deterministic_policy(networks):
    """`policy(params, obs) -> action`: the mode of the policy's action distribution, as the
    evaluation episodes act."""

    def policy(params: Params, obs: jax.Array) -> jax.Array:
        logits = networks.policy_network.apply(params.normalizer, params.policy, obs)
        return networks.parametric_action_distribution.mode(logits)

    return policy


def make_init(env: Locomotion, networks, cfg: PPOConfig):
    """`init(key) -> Params`: fresh parameters, one controller or K stacked along a leading axis."""

    def init_one(key: jax.Array) -> Params:
        key_policy, key_value = jax.random.split(key)
        obs_spec = jax.ShapeDtypeStruct((env.obs_size,), jnp.zeros(()).dtype)
        return Params(
            normalizer=running_statistics.init_state(obs_spec),
            policy=networks.policy_network.init(key_policy),
            value=networks.value_network.init(key_value),
        )

    def init(key: jax.Array) -> Params:
        if cfg.controllers == 1:
            return init_one(key)
        return jax.vmap(init_one)(jax.random.split(key, cfg.controllers))

    return init


def make_loss(networks, cfg: PPOConfig):
    """`loss_fn(net, normalizer, batch, advantages, targets, mask, key) -> (loss, entropy)`: the
    clipped PPO loss of one learner's minibatch (`Transition` of (M, ...) arrays, advantages and
    value targets (M,)), log-probabilities and entropy over the motors in `mask` (A,) only."""
    dist = networks.parametric_action_distribution
    policy_apply, value_apply = networks.policy_network.apply, networks.value_network.apply

    def loss_fn(net, normalizer, batch: Transition, advantages, targets, mask, key):
        logits = policy_apply(normalizer, net["policy"], batch.obs)
        log_prob = masked_log_prob(dist, logits, batch.raw_action, mask)
        ratio = jnp.exp(log_prob - batch.log_prob)
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
        clipped = jnp.clip(ratio, 1 - cfg.clip_eps, 1 + cfg.clip_eps)
        policy_loss = -jnp.mean(jnp.minimum(ratio * advantages, clipped * advantages))
        value = value_apply(normalizer, net["value"], batch.obs)
        value_loss = jnp.mean((targets - value) ** 2)
        entropy = jnp.mean(masked_entropy(dist, logits, key, mask))
        loss = policy_loss + cfg.vf_coef * value_loss - cfg.entropy_cost * entropy
        return loss, entropy

    return loss_fn
