"""Forward locomotion on a space's padded MJX model: planar, or in 3D for a free trunk.

The model is an argument of `reset` and `step`, never state on the task, so one task object
serves every morphology of a space and a batch of models vmaps through it. `reset_worlds` and
`step_worlds` do the same for a flat batch of worlds of different bodies on any physics engine
(`evojax_morph.physics.engines`), as the PPO fitness steps them; both paths share the task's code.
`rollout` steps either through an episode under a policy.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from evojax_morph.physics.engines import Engine
from evojax_morph.physics.templates import mjx
from evojax_morph.registry import Registry
from evojax_morph.spaces import Space


@dataclasses.dataclass(frozen=True)
class TaskConfig:
    """Locomotion task settings; `make_task(name)` gives the registered tasks' (`TASKS`), and
    the run command sets any field but the name as `--task.FIELD VALUE`.

    Attributes:
      name: the registered task these settings start from (`list_tasks`)
      frame_skip: physics steps (5 ms each) per control step: 50 Hz control
      episode_length: control steps per episode (5 s)
      ctrl_cost: weight of the squared controls of active motors
      forward_weight: weight of the trunk's forward velocity (m/s) per step
      healthy_reward: per step alive; 0 keeps a body that cannot move at fitness 0
      max_tilt: the episode terminates when the trunk tilts further than this (radians)
      min_height: the episode terminates when the trunk sinks below this fraction of its height
        at reset
      reset_noise: uniform noise on active joint angles and all velocities
      max_speed: a generalised velocity beyond this marks a diverged simulation
    """

    name: str = "distance"
    frame_skip: int = 4
    episode_length: int = 250
    ctrl_cost: float = 1e-3
    forward_weight: float = 1.0
    healthy_reward: float = 0.0
    max_tilt: float = 1.0
    min_height: float = 0.7
    reset_noise: float = 0.05
    max_speed: float = 100.0

    def __post_init__(self):
        if self.frame_skip < 1 or self.episode_length < 1:
            raise ValueError(f"a task needs frame_skip and episode_length of at least 1, got "
                             f"{self.frame_skip} and {self.episode_length}")
        if min(self.max_tilt, self.min_height, self.max_speed) <= 0 or self.reset_noise < 0:
            raise ValueError("a task needs max_tilt, min_height and max_speed above 0 and "
                             "reset_noise of at least 0")


# The registered tasks by their names, as mujoco_playground registers environments with their
# default configs. docs/fidelity.md says how each reads the source.
TASKS = Registry("task", (
    # The source's reading (NGE's fitness): the return pays the distance covered before the
    # episode ends, nothing for staying up, so falling forward is the easiest score.
    TaskConfig(name="distance"),
    # Walking: Gymnasium's Walker2d and Hopper terms (forward velocity, a reward per healthy
    # step, squared controls; the episode ends at a fall), the healthy reward scaled to these
    # bodies' speeds (docs/fidelity.md): standing still for 5 s pays 125, walking 2 m 225, a
    # lunge of 1 m that falls after 1 s 75.
    TaskConfig(name="walk", healthy_reward=0.5),
), sort=True)


# What "walks" means everywhere (the run's printout, docs/results.md): a body confirmed at a
# mean distance of at least WALK_METRES in an episode, upright the whole episode in at least
# WALK_UPRIGHT of its confirming evaluations. Any other body "moves" (its numbers said).
WALK_METRES = 2.0
WALK_UPRIGHT = 0.9


def gait_word(distance: float, upright_whole: float) -> str:
    """"walks" where a confirmed body meets the definition above, else "moves"."""
    return "walks" if distance >= WALK_METRES and upright_whole >= WALK_UPRIGHT else "moves"


def list_tasks() -> list[str]:
    """Names accepted by `make_task`, `TaskConfig.name` and the CLI's --task."""
    return TASKS.list()


def make_task(name: str, **overrides) -> TaskConfig:
    """The settings of the registered task `name`, with `overrides` (TaskConfig's fields).

    Raises:
      ValueError: `name` is not a registered task, or an override is not a setting.
    """
    task = TASKS.get(name)
    fields = {f.name for f in dataclasses.fields(TaskConfig)} - {"name"}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise ValueError(f"unknown task settings {unknown}; choose from {sorted(fields)}")
    return dataclasses.replace(task, **overrides)


class Body(NamedTuple):
    """What the task reads of a body's specialised model, per world."""

    motors: jax.Array  # (action_size,) bool: the motors the body has
    height: jax.Array  # (): the trunk's height at rest, above the floor


@struct.dataclass
class EnvState:
    data: mjx.Data
    obs: jax.Array  # (obs_size,)
    reward: jax.Array  # (): reward of the step that led here
    terminated: jax.Array  # () bool: fell over or diverged
    truncated: jax.Array  # () bool: reached episode_length alive
    steps: jax.Array  # () int32: control steps since reset
    diverged: jax.Array  # () bool: the simulation blew up (state non-finite or too fast)
    forward: jax.Array  # (): metres the trunk moved forward (+x) in the step that led here

    @property
    def done(self) -> jax.Array:
        return self.terminated | self.truncated


class Locomotion:
    """Move the trunk forward (+x): in the x-z plane, or in 3D where the trunk is free.

    Observation (6 + 2 x limbs): trunk height, sin and cos of its pitch, its x, z and pitch
      velocities, then every limb slot's joint angle and velocity (0 for inactive slots). For a
      free trunk (11 + 2 x limbs): its height, orientation (a quaternion) and 6 velocities
      (linear in the world frame, angular in its own), then the limbs'.
    Action (limbs): one control in [-1, 1] per motor slot; inactive slots are masked to 0.
    Reward: `forward_weight` x the trunk's forward velocity over the control step (m/s), plus
      `healthy_reward`, minus `ctrl_cost` x the sum of squared active controls.
    Termination (the walkers' healthy rules, made relative since bodies differ in size): the
      trunk pitches (tilts its up axis, in 3D) beyond `max_tilt` or sinks below `min_height` x
      its height at reset; or the simulation diverged (state not finite or a velocity beyond
      `max_speed`), which also zeroes that step's reward and observation.
    Truncation: after `episode_length` control steps.

    `limbs`, `full`: for a size class (`Space.size_classes`), the full template's limb slot of
    each of `space`'s limb slots, and the task on the full template: observations, actions and
    reset noise then keep the full template's layout (a slot this template lacks reads 0 and
    acts on nothing), so a controller means the same whichever template its body runs on, and
    a key resets a body alike on both.
    """

    def __init__(self, space: Space, cfg: TaskConfig = TaskConfig(),
                 limbs: np.ndarray | None = None, full: Locomotion | None = None):
        self.space, self.cfg = space, cfg
        t = space.template
        joint = lambda name: t.joint(name).id
        self._free = space.plan.root == "free"
        root = [joint(n) for n in space.plan.root_joints]
        if self._free:  # x, y, z, quaternion; 3 linear and 3 angular velocities
            self._root_qpos = t.jnt_qposadr[root[0]] + np.arange(7)
            self._root_dof = t.jnt_dofadr[root[0]] + np.arange(6)
        else:  # x, z, pitch
            self._root_qpos, self._root_dof = t.jnt_qposadr[root], t.jnt_dofadr[root]
        self._limb_qpos = np.array([t.jnt_qposadr[joint(n)] for n in space.plan.joint_names], int)
        self._limb_dof = np.array([t.jnt_dofadr[joint(n)] for n in space.plan.joint_names], int)
        self._actuator = np.array([t.actuator(n).id for n in space.plan.actuator_names], int)
        self._root_body = t.body("node0").id
        if t.nv != len(self._root_dof) + len(self._limb_dof):
            raise ValueError(f"{space.name}: every dof must be the root's or a limb joint's")
        own = len(self._actuator)
        self._limbs = np.arange(own) if limbs is None else np.asarray(limbs)  # into the layout
        self._layout = self if full is None else full  # the full template's
        self.action_size = own if full is None else full.action_size
        self.nv = t.nv
        self.obs_size = (11 if self._free else 6) + 2 * self.action_size
        self.dt = cfg.frame_skip * t.opt.timestep

    def action_mask(self, model: mjx.Model) -> jax.Array:
        """(action_size,) bool: the motors the morphology of `model` has."""
        own = model.actuator_gear[self._actuator, 0] != 0
        return jnp.zeros(self.action_size, bool).at[self._limbs].set(own)

    def body(self, model: mjx.Model) -> Body:
        """What the task reads of one specialised body (vmap it for a batch)."""
        return Body(self.action_mask(model), model.body_pos[self._root_body, 2])

    # ONE WORLD (JAX engine): the model is the body's own
    def reset(self, key: jax.Array, model: mjx.Model) -> EnvState:
        """A new episode: the body at rest above the floor, slightly perturbed."""
        data = mjx.make_data(model)
        qpos, qvel = self._perturb(key, self.body(model), data.qpos, data.qvel)
        data = mjx.forward(model, data.replace(qpos=qpos, qvel=qvel))
        return self._first(self.body(model), data.qpos, data.qvel).replace(data=data)

    def step(self, model: mjx.Model, state: EnvState, action: jax.Array) -> EnvState:
        """One control step of `frame_skip` physics steps."""
        body = self.body(model)
        action, ctrl = self._controls(body, state.data.ctrl, action)
        data = jax.lax.fori_loop(
            0, self.cfg.frame_skip, lambda _, d: mjx.step(model, d), state.data.replace(ctrl=ctrl)
        )
        outcome = self._outcome(body, state.data.qpos, state.steps, action, data.qpos, data.qvel)
        return outcome.replace(data=data)

    # A FLAT BATCH OF WORLDS on any engine (`evojax_morph.physics.engines`): N worlds, (N,) bodies
    def reset_worlds(self, engine: Engine, worlds, bodies: Body, keys: jax.Array) -> EnvState:
        """`reset` of N worlds at once: `worlds` from `engine.prepare`, `bodies` (N,) each
        world's `body`, keys (N,)."""
        data = engine.make_data(worlds, self.space, keys.shape[0])
        qpos, qvel = jax.vmap(self._perturb)(keys, bodies, data.qpos, data.qvel)
        data = engine.forward(worlds, data.replace(qpos=qpos, qvel=qvel))
        return jax.vmap(self._first)(bodies, data.qpos, data.qvel).replace(data=data)

    def step_worlds(
        self, engine: Engine, worlds, bodies: Body, state: EnvState, action: jax.Array
    ) -> EnvState:
        """`step` of N worlds at once; action (N, action_size)."""
        action, ctrl = jax.vmap(self._controls)(bodies, state.data.ctrl, action)
        data = engine.step(worlds, state.data.replace(ctrl=ctrl), self.cfg.frame_skip)
        outcome = jax.vmap(self._outcome)(
            bodies, state.data.qpos, state.steps, action, data.qpos, data.qvel
        )
        return outcome.replace(data=data)

    # THE TASK, per world, on positions and velocities
    def _perturb(self, key: jax.Array, body: Body, qpos: jax.Array, qvel: jax.Array):
        # Drawn over the full template's dofs and read at this template's: a body resets alike
        # on the full template and on its size class.
        key_q, key_v = jax.random.split(key)
        mask = body.motors.astype(qpos.dtype)
        full = self._layout
        noise_q = jax.random.uniform(key_q, (self.action_size,), minval=-1, maxval=1) * mask
        noise_v = jax.random.uniform(key_v, (full.nv,), minval=-1, maxval=1)
        root_v = noise_v[full._root_dof]
        limb_v = (noise_v[full._limb_dof] * mask)[self._limbs]
        noise = self.cfg.reset_noise
        qvel = qvel.at[self._root_dof].add(noise * root_v).at[self._limb_dof].add(noise * limb_v)
        if self._free:  # upright at the body's own height (qpos0 is one body's for a batch)
            start = jnp.array([0, 0, 0, 1, 0, 0, 0], qpos.dtype).at[2].set(body.height)
            qpos = qpos.at[self._root_qpos].set(start)
        return qpos.at[self._limb_qpos].add(noise * noise_q[self._limbs]), qvel

    def _obs(self, body: Body, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
        if self._free:
            trunk = qpos[self._root_qpos[2:]]  # height and orientation
        else:
            _, z, pitch = qpos[self._root_qpos]
            trunk = jnp.stack([z + body.height, jnp.sin(pitch), jnp.cos(pitch)])
        return jnp.concatenate(
            [
                trunk,
                qvel[self._root_dof],
                self._to_layout(qpos[self._limb_qpos]) * body.motors,
                self._to_layout(qvel[self._limb_dof]) * body.motors,
            ]
        )

    def _first(self, body: Body, qpos: jax.Array, qvel: jax.Array) -> EnvState:
        """The state after a reset, but its data (set by the caller: data is never vmapped)."""
        false = jnp.zeros((), bool)
        return EnvState(
            data=None,
            obs=self._obs(body, qpos, qvel),
            reward=jnp.zeros(()),
            terminated=false,
            truncated=false,
            steps=jnp.zeros((), jnp.int32),
            diverged=false,
            forward=jnp.zeros(()),
        )

    def _controls(self, body: Body, ctrl: jax.Array, action: jax.Array):
        action = jnp.where(body.motors, jnp.clip(action, -1.0, 1.0), 0.0)
        return action, ctrl.at[self._actuator].set(action[self._limbs])

    def _to_layout(self, x: jax.Array) -> jax.Array:
        """(limbs of this template,) -> (action_size,): zeros in the slots it lacks."""
        return jnp.zeros(self.action_size, x.dtype).at[self._limbs].set(x)

    def _outcome(self, body: Body, qpos_before, steps, action, qpos, qvel) -> EnvState:
        """The state after a control step, but its data (set by the caller)."""
        cfg = self.cfg
        forward = qpos[self._root_qpos[0]] - qpos_before[self._root_qpos[0]]
        reward = (cfg.forward_weight * forward / self.dt + cfg.healthy_reward
                  - cfg.ctrl_cost * jnp.sum(action**2))

        finite = jnp.isfinite(qpos).all() & jnp.isfinite(qvel).all()
        diverged = ~finite | (jnp.abs(qvel) > cfg.max_speed).any()
        obs = self._obs(body, qpos, qvel)
        reward = jnp.where(diverged | ~jnp.isfinite(reward), 0.0, reward)
        obs = jnp.where(diverged | ~jnp.isfinite(obs), 0.0, obs)
        if self._free:  # the trunk's up axis tilted from the vertical by more than max_tilt
            quat = qpos[self._root_qpos[3:]]
            _, qx, qy, _ = quat / jnp.linalg.norm(quat)
            tilted = 1 - 2 * (qx * qx + qy * qy) < jnp.cos(cfg.max_tilt)
            sunk = qpos[self._root_qpos[2]] < cfg.min_height * body.height
        else:
            tilted = jnp.abs(qpos[self._root_qpos[2]]) > cfg.max_tilt
            sunk = qpos[self._root_qpos[1]] + body.height < cfg.min_height * body.height
        terminated = tilted | sunk | diverged
        steps = steps + 1
        return EnvState(
            data=None,
            obs=obs,
            reward=reward,
            terminated=terminated,
            truncated=(steps >= cfg.episode_length) & ~terminated,
            steps=steps,
            diverged=diverged,
            forward=jnp.where(diverged | ~jnp.isfinite(forward), 0.0, forward),
        )


def rollout(step_fn, act_fn, first: EnvState, length: int, observe_fn, acc=None):
    """One episode of worlds under a policy: `length` control steps in one `lax.scan`.

    Every episode loop of the package is this one: PPO's evaluation episodes (a flat batch of
    worlds, `Locomotion.step_worlds`), a saved controller's replay and TAME's open-loop rollouts
    (one body's world, `Locomotion.step`).

    Args:
      step_fn: `step_fn(state, action) -> state`, one control step of the worlds.
      act_fn: `act_fn(state, t) -> action`, the policy; `t` the control step, a float32 ()
        counting from 0.
      first: the worlds' state after their reset: one world's (`Locomotion.reset`, fields ()) or
        a flat batch's (`Locomotion.reset_worlds`, fields (N,)), as `step_fn` takes it.
      length: control steps of the episode.
      observe_fn: `observe_fn(acc, state) -> (acc, out)` after each step: `state` the worlds'
        new state, `acc` what is summed up over the episode, `out` what is kept of each step
        (None: nothing).
      acc: the accumulator before the first step (a pytree; None: none).
    Returns:
      `(last, acc, outs)`: the state after `length` steps (however the episodes ended: the
      worlds step on after a fall, `observe_fn` masks what it sums), the accumulator after the
      last step, and each step's `out` stacked along a leading (length,) axis.
    """

    def control_step(carry, t):
        state, acc = carry
        state = step_fn(state, act_fn(state, t))
        acc, out = observe_fn(acc, state)
        return (state, acc), out

    (last, acc), outs = jax.lax.scan(
        control_step, (first, acc), jnp.arange(length, dtype=jnp.float32)
    )
    return last, acc, outs
