"""The evolution MDP as a Stable-Baselines3 `VecEnv`, for SB3 and sb3-contrib's `MaskablePPO`.

Needs the optional `stable-baselines3` (`pip install "evojax_morph[sb3]"`, which also brings
sb3-contrib and torch). SB3 takes its own `VecEnv`, not a Gymnasium `VectorEnv`; this one is a
thin layer over `GymEvolutionEnv`, so a step is still one batched fitness call for every
evolution.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from stable_baselines3.common.vec_env import VecEnv

from evojax_morph.envs.gym_env import GymEvolutionEnv


class SB3EvolutionEnv(VecEnv):
    """`GymEvolutionEnv`'s parallel evolutions as SB3's `VecEnv`: the same observation (a dict
    of (num_envs, ...) arrays, the action mask in it), actions, rewards and autoreset.

    Step: `step_wait` returns (obs, rewards (num_envs,) float32, dones (num_envs,) bool, infos):
      one dict per evolution with "fitness", "fitness_std", "diverged" and "action_valid" of
      the body evaluated and, where its episode ended (after `horizon` mutations), the last
      observation as "terminal_observation" (SB3's name for Gymnasium's `final_obs`) and
      "TimeLimit.truncated" False (episodes terminate, they are never cut). An ended evolution's
      observation is m0 again, as SB3 expects.
    Masks: `action_masks()` (num_envs, num_actions) bool; `env_method("action_masks")` gives its
      rows, one per evolution, which is how `MaskablePPO` asks.
    The evolutions share one environment: `get_attr` returns its attribute once per evolution,
    `set_attr` sets it for all, and `env_method` knows `action_masks` only.
    """

    def __init__(self, envs: GymEvolutionEnv):
        if not isinstance(envs, GymEvolutionEnv):
            raise TypeError(f"SB3EvolutionEnv wraps a GymEvolutionEnv, got {type(envs).__name__}")
        self.envs = envs
        self._actions = None
        super().__init__(envs.num_envs, envs.single_observation_space, envs.single_action_space)

    def reset(self):
        """Every evolution at m0 (one batched fitness call); the seed of `seed(s)`, if given
        since the last reset, seeds it (the evolutions share the first)."""
        obs, info = self.envs.reset(seed=self._seeds[0])
        self._reset_seeds()
        self._reset_options()
        self.reset_infos = _split(info, self.num_envs)
        return _writable(obs)

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions).reshape(self.num_envs).astype(np.int64)

    def step_wait(self):
        if self._actions is None:
            raise RuntimeError("call step_async(actions) before step_wait()")
        actions, self._actions = self._actions, None
        obs, reward, terminated, truncated, info = self.envs.step(actions)
        final = info.pop("final_obs", None)
        info.pop("_final_obs", None)
        infos = _split(info, self.num_envs)
        dones = terminated | truncated
        for i in np.flatnonzero(dones):
            infos[i]["terminal_observation"] = final[i]
            infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
        return _writable(obs), reward.astype(np.float32), dones, infos

    def action_masks(self) -> np.ndarray:
        """(num_envs, num_actions) bool: the valid actions of the current observation."""
        return self.envs.action_masks()

    def close(self) -> None:
        self.envs.close()

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        value = getattr(self.envs, attr_name)
        return [value for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        if indices is not None and sorted(self._get_indices(indices)) != list(
            range(self.num_envs)
        ):
            raise ValueError("the evolutions share one environment: set an attribute for all")
        setattr(self.envs, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs):
        if method_name != "action_masks":
            raise AttributeError(
                f"env_method({method_name!r}): the evolutions are one batched environment; "
                "only 'action_masks' is answered per evolution"
            )
        masks = self.action_masks()
        return [masks[i] for i in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [None for _ in range(self.num_envs)]


def _split(info: dict, n: int) -> list[dict]:
    """Gymnasium's dict of (n,) arrays as SB3's list of n dicts."""
    return [{k: v[i] for k, v in info.items() if not k.startswith("_")} for i in range(n)]


def _writable(obs: dict) -> dict:
    """Copies of the host arrays (JAX's are read-only, which torch warns of)."""
    return {k: np.array(v) for k, v in obs.items()}
