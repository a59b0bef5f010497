"""The evolution MDP as a Gymnasium vector environment, for agents written for Gymnasium.

Needs the optional `gymnasium` package (`pip install "evojax_morph[gym]"`).
"""

from __future__ import annotations

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from evojax_morph.fitnesses import FitnessConfig
from evojax_morph.fitnesses.batched import make_env
from evojax_morph.mdp import Observation
from evojax_morph.spaces import Space, make_space


class GymEvolutionEnv(gym.vector.VectorEnv):
    """`num_envs` parallel evolutions of a space (`EvolutionEnv`); a step is one batched
    fitness call for all of them.

    Observation (a dict, each entry with a leading (num_envs,) axis): the padded morphology,
      "active" (max_nodes,) int8, "parent" (max_nodes,) int32 (-1: none), "kind" and "site"
      (max_nodes,) int32, "attrs" (max_nodes, num_attrs) float32; "progress" (1,) float32,
      the mutations done this episode / horizon; "action_mask" (num_actions,) int8, the valid
      actions (also `action_masks()`, as maskable agents such as sb3-contrib's expect).
    Action: Discrete(max_nodes x num_mutations) per evolution, node * num_mutations +
      mutation. A masked action is a no-op (the body is evaluated again unchanged) and
      `info["action_valid"]` is False for it.
    Reward: f(child) - f(parent).
    Termination: after `horizon` mutations; never truncated. Autoreset in the same step
      (`AutoresetMode.SAME_STEP`): an ended evolution's observation is m0 again, as the first
      reset evaluated it (no new fitness call), and its last observation is in
      `info["final_obs"]` (an object array, None for the others, with mask `info["_final_obs"]`).
    Info: "fitness", "fitness_std", "diverged" of the bodies evaluated, and "action_valid".

    Every array lives on the host as numpy; the fitness and the mutations run in one jitted
    call per step. `reset(seed=None)` before any seeded reset uses seed 0.
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(
        self,
        space: Space | str = "bad_walker",
        fitness: FitnessConfig | str = FitnessConfig(),
        num_envs: int = 8,
        horizon: int | None = None,
        mesh=None,
    ):
        self.space = make_space(space) if isinstance(space, str) else space
        self.fitness = FitnessConfig(kind=fitness) if isinstance(fitness, str) else fitness
        self.env = make_env(self.space, self.fitness, num_envs, horizon, mesh)
        self.num_envs = num_envs
        self.render_mode = None

        s = self.space
        n, nodes = s.num_actions, s.max_nodes
        index = lambda names: spaces.Box(0, len(names) - 1, (nodes,), np.int32)  # noqa: E731
        self.single_observation_space = spaces.Dict({
            "active": spaces.MultiBinary(nodes),
            "parent": spaces.Box(-1, nodes - 1, (nodes,), np.int32),
            "kind": index(s.kind_names),
            "site": index(s.site_names),
            "attrs": spaces.Box(-np.inf, np.inf, (nodes, len(s.attr_names)), np.float32),
            "progress": spaces.Box(0.0, 1.0, (1,), np.float32),
            "action_mask": spaces.MultiBinary(n),
        })
        self.single_action_space = spaces.Discrete(n)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)

        self._reset = jax.jit(self.env.reset)
        self._step = jax.jit(self._step_and_restart)
        self._key = jax.random.PRNGKey(0)
        self._state = self._first = self._obs = None

    def _step_and_restart(self, key, state, first, action):
        """One step of every evolution, the ended ones restarted at `first`."""
        valid = self.env.observe(state).mask[jnp.arange(self.num_envs), action]
        final_obs, new, reward, terminated, truncated, _ = self.env.step(key, state, action)
        restarted = self.env.auto_reset(new, first, terminated | truncated)
        obs = self.env.observe(restarted)
        return obs, restarted, reward, terminated, truncated, final_obs, new, valid

    def _to_numpy(self, obs: Observation) -> dict:
        obs, m = jax.device_get(obs), jax.device_get(obs.morph)
        return {
            "active": np.asarray(m.active, np.int8),
            "parent": np.asarray(m.parent, np.int32),
            "kind": np.asarray(m.kind, np.int32),
            "site": np.asarray(m.site, np.int32),
            "attrs": np.asarray(m.attrs, np.float32),
            "progress": np.asarray(obs.progress, np.float32)[:, None],
            "action_mask": np.asarray(obs.mask, np.int8),
        }

    @staticmethod
    def _info(evaluated) -> dict:
        fitness, std, diverged = jax.device_get(
            (evaluated.fitness, evaluated.fitness_std, evaluated.diverged)
        )
        return {"fitness": np.asarray(fitness), "fitness_std": np.asarray(std),
                "diverged": np.asarray(diverged)}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Every evolution at m0, its controller trained from scratch and its fitness measured
        (one batched fitness call); m0 as evaluated here is where ended episodes restart."""
        super().reset(seed=seed)
        if seed is not None:
            self._key = jax.random.PRNGKey(seed)
        self._key, key = jax.random.split(self._key)
        obs, self._state = self._reset(key)
        self._first = self._state
        self._obs = self._to_numpy(obs)
        return self._obs, self._info(self._state)

    def step(self, actions):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        actions = np.asarray(actions)
        if actions.shape != (self.num_envs,) or not np.issubdtype(actions.dtype, np.integer):
            raise ValueError(f"actions must be {self.num_envs} integers, got {actions!r}")
        if ((actions < 0) | (actions >= self.space.num_actions)).any():
            raise ValueError(f"actions must lie in 0..{self.space.num_actions - 1}: {actions}")
        self._key, key = jax.random.split(self._key)
        obs, self._state, reward, terminated, truncated, final_obs, evaluated, valid = self._step(
            key, self._state, self._first, jnp.asarray(actions, jnp.int32)
        )
        terminated, truncated = np.asarray(terminated), np.asarray(truncated)
        info = {**self._info(evaluated), "action_valid": np.asarray(valid)}
        done = terminated | truncated
        if done.any():
            final = self._to_numpy(final_obs)
            info["final_obs"] = np.array(
                [{k: v[i] for k, v in final.items()} if done[i] else None
                 for i in range(self.num_envs)], dtype=object
            )
            info["_final_obs"] = done
        self._obs = self._to_numpy(obs)
        return self._obs, np.asarray(reward), terminated, truncated, info

    def action_masks(self) -> np.ndarray:
        """(num_envs, num_actions) bool: the valid actions of the current observation."""
        if self._state is None:
            raise RuntimeError("call reset() before action_masks()")
        return self._obs["action_mask"].astype(bool)
