"""Planar forward locomotion on a space's padded MJX model.

The model is an argument of `reset` and `step`, never state on the task, so one task object
serves every morphology of a space and a batch of models vmaps through it.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from evojax_morph.physics import ROOT_JOINTS, mjx
from evojax_morph.spaces import Space


@dataclasses.dataclass(frozen=True)
class TaskConfig:
    """Locomotion task settings."""

    frame_skip: int = 4  # physics steps (5 ms each) per control step: 50 Hz control
    episode_length: int = 250  # control steps per episode (5 s)
    ctrl_cost: float = 1e-3  # weight of the squared controls of active motors
    healthy_reward: float = 0.0  # per step; 0 keeps a body that cannot move at fitness 0
    max_tilt: float = 1.0  # rad: the episode terminates when the trunk tilts further...
    min_height: float = 0.7  # ...or sinks below this fraction of its height at reset
    reset_noise: float = 0.05  # uniform noise on active joint angles and all velocities
    max_speed: float = 100.0  # a generalised velocity beyond this marks a diverged simulation


@struct.dataclass
class EnvState:
    data: mjx.Data
    obs: jax.Array  # (obs_size,)
    reward: jax.Array  # (): reward of the step that led here
    terminated: jax.Array  # () bool: fell over or diverged
    truncated: jax.Array  # () bool: reached episode_length alive
    steps: jax.Array  # () int32: control steps since reset
    diverged: jax.Array  # () bool: the simulation blew up (state non-finite or too fast)

    @property
    def done(self) -> jax.Array:
        return self.terminated | self.truncated


class Locomotion:
    """Move the trunk forward (+x) in the x-z plane.

    Observation (6 + 2 x limbs): trunk height, sin and cos of its pitch, its x, z and pitch
      velocities, then every limb slot's joint angle and velocity (0 for inactive slots).
    Action (limbs): one control in [-1, 1] per motor slot; inactive slots are masked to 0.
    Reward: forward velocity of the trunk over the control step (m/s), plus `healthy_reward`,
      minus `ctrl_cost` x sum of squared active controls.
    Termination (the walkers' healthy rules, made relative since bodies differ in size): the
      trunk pitches beyond `max_tilt` or sinks below `min_height` x its height at reset; or the
      simulation diverged (state not finite or a velocity beyond `max_speed`), which also
      zeroes that step's reward and observation.
    Truncation: after `episode_length` control steps.
    """

    def __init__(self, space: Space, cfg: TaskConfig = TaskConfig()):
        self.space, self.cfg = space, cfg
        t = space.template
        joint = lambda name: t.joint(name).id
        self._root_qpos = np.array([t.jnt_qposadr[joint(n)] for n in ROOT_JOINTS])
        self._root_dof = np.array([t.jnt_dofadr[joint(n)] for n in ROOT_JOINTS])
        self._limb_qpos = np.array([t.jnt_qposadr[joint(n)] for n in space.plan.joint_names], int)
        self._limb_dof = np.array([t.jnt_dofadr[joint(n)] for n in space.plan.joint_names], int)
        self._actuator = np.array([t.actuator(n).id for n in space.plan.actuator_names], int)
        self._root_body = t.body("node0").id
        self.action_size = len(self._actuator)
        self.obs_size = 6 + 2 * self.action_size
        self.dt = cfg.frame_skip * t.opt.timestep

    def action_mask(self, model: mjx.Model) -> jax.Array:
        """(action_size,) bool: the motors the morphology of `model` has."""
        return model.actuator_gear[self._actuator, 0] != 0

    def _obs(self, model: mjx.Model, data: mjx.Data) -> jax.Array:
        mask = self.action_mask(model)
        _, z, pitch = data.qpos[self._root_qpos]
        height = z + model.body_pos[self._root_body, 2]
        return jnp.concatenate(
            [
                jnp.stack([height, jnp.sin(pitch), jnp.cos(pitch)]),
                data.qvel[self._root_dof],
                data.qpos[self._limb_qpos] * mask,
                data.qvel[self._limb_dof] * mask,
            ]
        )

    def reset(self, key: jax.Array, model: mjx.Model) -> EnvState:
        """A new episode: the body at rest above the floor, slightly perturbed."""
        cfg = self.cfg
        key_q, key_v = jax.random.split(key)
        data = mjx.make_data(model)
        mask = self.action_mask(model).astype(data.qpos.dtype)
        noise_q = jax.random.uniform(key_q, (self.action_size,), minval=-1, maxval=1) * mask
        dof_on = jnp.ones(model.nv).at[self._limb_dof].set(mask)
        noise_v = jax.random.uniform(key_v, (model.nv,), minval=-1, maxval=1) * dof_on
        data = data.replace(
            qpos=data.qpos.at[self._limb_qpos].add(cfg.reset_noise * noise_q),
            qvel=data.qvel + cfg.reset_noise * noise_v,
        )
        data = mjx.forward(model, data)
        false = jnp.zeros((), bool)
        return EnvState(
            data=data,
            obs=self._obs(model, data),
            reward=jnp.zeros(()),
            terminated=false,
            truncated=false,
            steps=jnp.zeros((), jnp.int32),
            diverged=false,
        )

    def step(self, model: mjx.Model, state: EnvState, action: jax.Array) -> EnvState:
        """One control step of `frame_skip` physics steps."""
        cfg = self.cfg
        mask = self.action_mask(model)
        action = jnp.where(mask, jnp.clip(action, -1.0, 1.0), 0.0)
        ctrl = state.data.ctrl.at[self._actuator].set(action)
        x_before = state.data.qpos[self._root_qpos[0]]
        data = jax.lax.fori_loop(
            0, cfg.frame_skip, lambda _, d: mjx.step(model, d), state.data.replace(ctrl=ctrl)
        )
        forward_velocity = (data.qpos[self._root_qpos[0]] - x_before) / self.dt
        reward = forward_velocity + cfg.healthy_reward - cfg.ctrl_cost * jnp.sum(action**2)

        finite = jnp.isfinite(data.qpos).all() & jnp.isfinite(data.qvel).all()
        diverged = ~finite | (jnp.abs(data.qvel) > cfg.max_speed).any()
        obs = self._obs(model, data)
        reward = jnp.where(diverged | ~jnp.isfinite(reward), 0.0, reward)
        obs = jnp.where(diverged | ~jnp.isfinite(obs), 0.0, obs)
        tilted = jnp.abs(data.qpos[self._root_qpos[2]]) > cfg.max_tilt
        start_height = model.body_pos[self._root_body, 2]
        sunk = data.qpos[self._root_qpos[1]] + start_height < cfg.min_height * start_height
        terminated = tilted | sunk | diverged
        steps = state.steps + 1
        return EnvState(
            data=data,
            obs=obs,
            reward=reward,
            terminated=terminated,
            truncated=(steps >= cfg.episode_length) & ~terminated,
            steps=steps,
            diverged=diverged,
        )
