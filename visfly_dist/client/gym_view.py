"""Gymnasium views of a :class:`~visfly_dist.client.env_base.DroneEnvBase` (which is an SB3 VecEnv).

- :class:`GymnasiumVectorView`: a ``gymnasium.vector.VectorEnv`` with
  ``metadata["autoreset_mode"] == AutoresetMode.SAME_STEP``: a done agent's returned observation is
  already the first of its next episode; its last one is in ``infos["final_obs"][i]`` and its step
  info in ``infos["final_info"]`` (masks ``infos["_final_obs"]``, ``infos["_final_info"]``). This is
  SB3's auto-reset semantics under Gymnasium's names.
- :class:`SingleAgentView`: a ``gymnasium.Env`` over a one-agent env, for tools that take a single
  env (``gymnasium.utils.env_checker.check_env``, SB3's ``check_env``).

Both share the wrapped env: closing a view closes it.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from visfly_dist.errors import ConfigError

_SB3_ONLY_KEYS = ("terminal_observation", "TimeLimit.truncated", "episode")


def _split_info(info: dict[str, Any]) -> tuple[dict[str, Any], bool]:
    """Step info without SB3's bookkeeping keys, and whether the step was a truncation."""
    return {k: v for k, v in info.items() if k not in _SB3_ONLY_KEYS}, bool(info.get("TimeLimit.truncated", False))


class GymnasiumVectorView(VectorEnv):
    """The env as a Gymnasium vector env (SAME_STEP autoreset)."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, env: Any) -> None:
        self.env = env
        self.num_envs = env.num_envs
        self.single_observation_space = env.observation_space
        self.single_action_space = env.action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.render_mode = None

    def reset(self, *, seed: int | list[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Reset every agent; ``seed`` (an int, or a list whose first entry is used) reseeds the env."""
        if isinstance(seed, (list, tuple)):
            seed = seed[0]
        if seed is not None:
            self.env.seed(int(seed))
        return self.env.reset(), {}

    def step(self, actions: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        obs, rewards, dones, sb3_infos = self.env.step(np.asarray(actions, dtype=np.float32))
        truncated = np.zeros(self.num_envs, dtype=bool)
        infos: dict[str, Any] = {}
        for i, sb3_info in enumerate(sb3_infos):
            info, truncated[i] = _split_info(sb3_info)
            if dones[i]:
                infos = self._add_info(infos, {"final_obs": sb3_info["terminal_observation"], "final_info": info}, i)
            infos = self._add_info(infos, info, i)
        terminated = np.asarray(dones, dtype=bool) & ~truncated
        return obs, np.asarray(rewards, dtype=np.float64), terminated, truncated, infos

    def close_extras(self, **kwargs: Any) -> None:
        self.env.close()


class SingleAgentView(gymnasium.Env):
    """A one-agent env as a ``gymnasium.Env`` (terminal observation returned, reset on demand)."""

    metadata = {"render_modes": []}

    def __init__(self, env: Any) -> None:
        if env.num_envs != 1:
            raise ConfigError(f"as_gymnasium_env() needs num_envs=1, got num_envs={env.num_envs}; "
                              "use as_gymnasium() for a vector env")
        self.env = env
        self.observation_space = env.observation_space
        self.action_space = env.action_space
        self.render_mode = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict[str, np.ndarray], dict]:
        super().reset(seed=seed)
        if seed is not None:
            self.env.seed(int(seed))
        return {k: v[0] for k, v in self.env.reset().items()}, {}

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        obs, rewards, dones, infos = self.env.step(np.asarray(action, dtype=np.float32)[None])
        info, truncated = _split_info(infos[0])
        if dones[0]:
            return dict(infos[0]["terminal_observation"]), float(rewards[0]), not truncated, truncated, info
        return {k: v[0] for k, v in obs.items()}, float(rewards[0]), False, False, info

    def close(self) -> None:
        self.env.close()
