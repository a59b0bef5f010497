"""Quantile-regression DQN (Dabney et al. 2018) over mutations: the distributional agent.

The Double-DQN's GNN (`dqn.q_network`) gives `quantiles` values per (node, mutation) instead of
one: the quantiles at midpoints tau_i = (2i + 1) / (2 * quantiles) of the return's distribution.
They are learned with the quantile Huber loss against a Double-DQN target: the online network
picks the next action by the mean of its quantiles over valid actions, the target network gives
that action's quantiles. Acting (epsilon-greedy on the mean), the replay buffer and the update
schedule are the Double-DQN's (`dqn.replay_policy`).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from evojax_morph.agents import dqn
from evojax_morph.agents.base import Policy
from evojax_morph.mdp import EvolutionEnv, masked_argmax


@dataclasses.dataclass(frozen=True)
class QRDQNConfig(dqn.DQNConfig):
    """Double-DQN's settings (`dqn.DQNConfig`, `for_run` included) and the quantiles."""

    quantiles: int = 32  # quantiles of the return per action
    kappa: float = 1.0  # the Huber loss's threshold


def quantile_midpoints(n: int) -> jax.Array:
    """(n,) tau_i = (2i + 1) / 2n: the fractions whose quantiles the network outputs."""
    return (2.0 * jnp.arange(n) + 1.0) / (2.0 * n)


def quantile_target(reward, terminal, discount, z_next_online, z_next_target, next_mask):
    """r + gamma (1 - terminal) Z_target(s', a*), a* the valid a' of highest mean Z_online(s', a').

    Args:
      reward, terminal: (B,) float.
      z_next_online, z_next_target: (B, A, N) quantiles of s' by the online and target networks.
      next_mask: (B, A) bool, the valid actions in s'.
    Returns:
      (B, N) target quantiles (r alone where s' has no valid action).
    """
    best = masked_argmax(z_next_online.mean(-1), next_mask)
    z = jnp.take_along_axis(z_next_target, best[:, None, None], 1)[:, 0]  # (B, N)
    z = jnp.where(next_mask.any(-1, keepdims=True), z, 0.0)  # nothing to bootstrap
    return reward[:, None] + discount * (1.0 - terminal[:, None]) * z


def quantile_huber_loss(z, target, kappa: float = 1.0):
    """Quantile Huber loss of predicted quantiles against target samples.

    sum_i mean_j |tau_i - 1{u_ij < 0}| L_kappa(u_ij) / kappa, with u_ij = target_j - z_i and
    L_kappa the Huber loss (u^2 / 2 within kappa, kappa (|u| - kappa / 2) beyond).

    Args:
      z: (B, N) predicted quantiles at `quantile_midpoints(N)`.
      target: (B, M) target samples (no gradient flows into them).
      kappa: the Huber threshold.
    Returns:
      (B,) losses.
    """
    u = jax.lax.stop_gradient(target)[:, None, :] - z[:, :, None]  # (B, N, M)
    abs_u = jnp.abs(u)
    huber = jnp.where(abs_u <= kappa, 0.5 * u**2, kappa * (abs_u - 0.5 * kappa))
    tau = quantile_midpoints(z.shape[-1])[None, :, None]
    weight = jnp.abs(tau - (u < 0).astype(z.dtype))
    return jnp.sum(jnp.mean(weight * huber / kappa, -1), -1)


def make_policy(env: EvolutionEnv, cfg: QRDQNConfig) -> Policy:
    """QR-DQN's acting and learning; scores are the mean quantiles (the Q-values)."""
    init_net, z_fn = dqn.q_network(env.space, cfg, cfg.quantiles)  # (N, A, quantiles)
    q_fn = lambda params, obs: z_fn(params, obs).mean(-1, keepdims=True)  # noqa: E731  one head

    def loss_fn(params, target_params, batch):
        obs, action, reward, next_obs, terminal, _ = batch  # one head: every transition trains it
        z = z_fn(params, obs)
        z_taken = jnp.take_along_axis(z, action[:, None, None], 1)[:, 0]  # (B, N)
        target = quantile_target(
            reward,
            terminal.astype(z.dtype),
            cfg.discount,
            z_fn(params, next_obs),
            z_fn(target_params, next_obs),
            next_obs.mask,
        )
        return jnp.mean(quantile_huber_loss(z_taken, target, cfg.kappa))

    return dqn.replay_policy(env, cfg, init_net, q_fn, loss_fn)
