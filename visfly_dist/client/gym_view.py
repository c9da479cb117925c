"""Gymnasium views of a :class:`~visfly_dist.client.env_base.DroneEnvBase` (which is an SB3 VecEnv).

- :class:`GymnasiumVectorView`: a ``gymnasium.vector.VectorEnv``, NEXT_STEP autoreset by default
  (what Gymnasium's own vector wrappers accept), SAME_STEP on request (SB3's semantics under
  Gymnasium's names: ``infos["final_obs"]`` and ``infos["final_info"]``).
- :class:`SingleAgentView`: a ``gymnasium.Env`` over a one-agent env, for tools that take a single
  env (``gymnasium.utils.env_checker.check_env``, SB3's ``check_env``).

Both share the wrapped env: closing a view closes it.
"""

from __future__ import annotations

import secrets
from typing import Any

import gymnasium
import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from visfly_dist.client.core import combined_seed
from visfly_dist.errors import ConfigError

_SB3_ONLY_KEYS = ("terminal_observation", "TimeLimit.truncated", "episode")


def _split_info(info: dict[str, Any]) -> tuple[dict[str, Any], bool]:
    """Step info without SB3's bookkeeping keys, and whether the step was a truncation."""
    return {k: v for k, v in info.items() if k not in _SB3_ONLY_KEYS}, bool(info.get("TimeLimit.truncated", False))


class GymnasiumVectorView(VectorEnv):
    """The env as a Gymnasium vector env.

    Args:
        env: the env (shared: closing the view closes it).
        autoreset_mode: ``NEXT_STEP`` (Gymnasium's default, accepted by its vector wrappers such as
            ``FlattenObservation``): a done agent returns its last observation; on the next step
            it is reset (its action ignored) and returns its first one, reward 0, not done.
            ``SAME_STEP``: the returned observation is already the next episode's first, the last
            one is in ``infos["final_obs"]`` (SB3's semantics under Gymnasium's names).

    ``reset(seed=...)`` takes an int ``s`` (sub-env ``i`` gets ``s + i``, as in Gymnasium's own vector
    envs) or one seed per sub-env (a list of length ``num_envs``; ``None`` entries draw fresh
    entropy). A sub-env's starts follow its own seed only, whatever the others' seeds or histories.
    Sensor noise is drawn for all sub-envs at once, from one generator seeded by the whole list.
    ``options={"reset_mask": m}`` resets only the sub-envs where the bool array ``m`` is True (and
    a seed then reseeds only those).
    """

    def __init__(self, env: Any, autoreset_mode: AutoresetMode = AutoresetMode.NEXT_STEP) -> None:
        if autoreset_mode not in (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP):
            raise ConfigError(f"autoreset_mode={autoreset_mode!r} must be AutoresetMode.NEXT_STEP or SAME_STEP")
        self.env = env
        self.metadata = {"autoreset_mode": autoreset_mode, "render_modes": []}
        self.num_envs = env.num_envs
        self.single_observation_space = env.observation_space
        self.single_action_space = env.action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.render_mode = None
        self._autoreset = np.zeros(self.num_envs, dtype=bool)  # NEXT_STEP: reset on the coming step

    def reset(self, *, seed: int | list[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Reset every agent, or those of ``options["reset_mask"]``; see the class docstring for ``seed``."""
        mask = None if options is None else options.get("reset_mask")
        if mask is not None:
            mask = np.asarray(mask)
            if mask.dtype != np.bool_ or mask.shape != (self.num_envs,) or not mask.any():
                raise ValueError(f"options['reset_mask'] must be a bool array of shape ({self.num_envs},) with at "
                                 f"least one True, got dtype {mask.dtype} shape {mask.shape}")
        seeds = self._seed_list(seed)
        if seeds is not None:
            self._np_random_seed = combined_seed(seeds) if isinstance(seed, (list, tuple)) else seeds[0]
            self._np_random = np.random.default_rng(self._np_random_seed)
        if mask is None:
            self._autoreset[:] = False
            if seeds is not None:
                self.env._reseed(seeds)
            return self.env.reset(), {}
        self._autoreset[mask] = False
        return self.env.reset_some(mask, None if seeds is None else [seeds[i] for i in np.flatnonzero(mask)]), {}

    def _seed_list(self, seed: int | list[int | None] | None) -> list[int] | None:
        """One seed per sub-env: ``seed + i`` for an int (as Gymnasium's own vector envs do), the
        list's entries (``None``: fresh entropy) for a list; ``None`` for no seed."""
        if seed is None:
            return None
        if isinstance(seed, (list, tuple)):
            if len(seed) != self.num_envs:
                raise ValueError(f"a seed list must have one seed per sub-env: num_envs={self.num_envs}, "
                                 f"got length {len(seed)}")
            return [_checked_seed(s) if s is not None else secrets.randbits(63) for s in seed]
        return [_checked_seed(seed) + i for i in range(self.num_envs)]

    def step(self, actions: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        env = self.env
        hold = None
        if self.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP and self._autoreset.any():
            hold = torch.as_tensor(self._autoreset, device=env.device)
        obs_t, reward_t, terminated_t, truncated_t, info = env.step_tensor(
            torch.as_tensor(np.asarray(actions, dtype=np.float32), device=env.device), hold=hold)
        obs = env.to_numpy(obs_t)
        rewards = reward_t.detach().cpu().numpy().astype(np.float64)
        terminated, truncated = terminated_t.cpu().numpy(), truncated_t.cpu().numpy()
        done = terminated | truncated
        infos = self._step_infos(info)
        if done.any():
            final = env.to_numpy(info["terminal_observation"])
            if self.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP:
                for key, value in obs.items():  # the last observation now, the first one next step
                    value[done] = final[key][done]
            else:
                final_info = dict(infos)  # this step's infos, before the final entries join them
                infos["final_obs"] = np.array([{k: v[i] for k, v in final.items()} if done[i] else None
                                               for i in range(self.num_envs)], dtype=object)
                infos["_final_obs"] = done.copy()
                infos["final_info"] = final_info
                infos["_final_info"] = done.copy()
        self._autoreset = done.copy()
        return obs, rewards, terminated, truncated, infos

    def _step_infos(self, info: dict[str, Any]) -> dict[str, Any]:
        """Per-agent flags of the step as Gymnasium vector infos (``key`` and its ``_key`` mask)."""
        out: dict[str, Any] = {}
        for key, name in (("success", "is_success"), ("collision", "collision"), ("out_of_bounds", "out_of_bounds"),
                          ("lost", "lost"), ("held", "held"), ("swapped", "swapped")):
            out[name] = info[key].detach().cpu().numpy().astype(bool)
            out[f"_{name}"] = np.ones(self.num_envs, dtype=bool)
        return out

    def render(self) -> None:
        """Nothing: the view has no render mode (``render_mode`` is ``None``), as Gymnasium's envs
        without one. Images are in the observation; ``visfly-dist eval`` writes videos."""
        return None

    def close_extras(self, **kwargs: Any) -> None:
        self.env.close()


def _checked_seed(seed: Any) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"a seed must be a non-negative int, got {seed!r}")
    return int(seed)


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

    def render(self) -> None:
        """Nothing: no render mode (``render_mode`` is ``None``); see :meth:`GymnasiumVectorView.render`."""
        return None

    def close(self) -> None:
        self.env.close()
