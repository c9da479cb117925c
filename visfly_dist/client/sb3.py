"""The SB3 ``VecEnv`` view of the tensor env: numpy observations, one info dict per agent.

:class:`SB3VecEnv` adds to :class:`~visfly_dist.client.core.TensorEnv` only what SB3's contract
asks for (``reset``/``step_async``/``step_wait`` with numpy, the terminal observation and episode
figures in per-agent info dicts, ``get_attr``/``env_method``, seeding through ``VecEnv.seed``); the
state, the step and the resets are the core's.
"""

from __future__ import annotations

import itertools
import time
from typing import Any, Iterable, Sequence

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv

from visfly_dist.client.core import StepResult, TensorEnv
from visfly_dist.errors import ConfigError

_QUIET_INFO = {"is_success": False, "collision": False, "out_of_bounds": False, "TimeLimit.truncated": False}
"""The SB3 info of a row with no flag set (copied per row and step: SB3 wants fresh dicts)."""


class SB3VecEnv(TensorEnv, VecEnv):  # type: ignore[misc]  # spaces: Dict/Box here, Space in VecEnv
    """The tensor env as a Stable-Baselines3 ``VecEnv`` (see the module docstring)."""

    _pending_actions: torch.Tensor | None = None

    def _init_views(self, num_envs: int, observation_space: spaces.Dict, action_space: spaces.Box) -> None:
        VecEnv.__init__(self, num_envs, observation_space, action_space)
        self._t0 = time.time()   # episode end times in the infos count from here

    def _first_reset(self) -> None:
        self.reset()

    def reset(self) -> dict[str, np.ndarray]:
        """Reset every agent (seeded by the last ``seed()`` call, if any); numpy observation.

        Groups still in flight (:meth:`send`) are taken in and dropped: their step never happened."""
        seeds = [int(s) for s in self._seeds if s is not None] if self._seeds[0] is not None else None
        self._reset_seeds()
        self._reset_options()
        obs = self.reset_tensor(seeds)
        self.reset_infos = [{} for _ in range(self.num_envs)]
        return self.to_numpy(obs)

    def reset_some(self, mask: torch.Tensor | np.ndarray, seeds: Sequence[int] | None = None) -> dict[str, np.ndarray]:
        """Reset only the agents in ``mask`` (``(N,)`` bool); the numpy observation of every agent
        (a full :meth:`reset` before the first one). ``seeds``: as :meth:`TensorEnv.reset_some_tensor`."""
        if self.frame is None:
            self._check_open()
            self._check_no_flight("reset_some()")
            return self.reset()
        return self.to_numpy(self.reset_some_tensor(mask, seeds))

    def get_images(self) -> list[None]:
        """One ``None`` per agent: the env has no render mode, as SB3's ``DummyVecEnv`` answers
        without one. Images are in the observation; ``visfly-dist eval`` writes videos."""
        return [None] * self.num_envs

    def step_async(self, actions: np.ndarray) -> None:
        self._pending_actions = torch.as_tensor(np.asarray(actions), dtype=torch.float32, device=self.device)

    def step_wait(self) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, list[dict[str, Any]]]:
        assert self._pending_actions is not None, "step_wait() without step_async()"
        actions, self._pending_actions = self._pending_actions, None
        return self.to_sb3(self.step_tensor(actions))

    def to_sb3(self, result: StepResult) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, list[dict[str, Any]]]:
        """A step's result as SB3's ``VecEnv.step`` returns it: numpy observation, rewards, dones and
        one info dict per row (every agent after :meth:`step_tensor`, a group's rows after :meth:`recv`).
        A done row's ``terminal_observation`` holds copies of its own rows, nothing else."""
        obs, reward, terminated, truncated, info = result
        return (self.to_numpy(obs), reward.detach().cpu().numpy().astype(np.float32),
                (terminated | truncated).cpu().numpy(), self._sb3_infos(terminated, truncated, info))

    def _sb3_infos(self, terminated: torch.Tensor, truncated: torch.Tensor, info: dict[str, Any]) -> list[dict[str, Any]]:
        """One fresh info dict per row; a done row also gets its terminal observation (a copy of
        its own rows only) and its episode's return, length and end flags; a held row (its worker
        failed; see :class:`~visfly_dist.client.core.StepResult`) gets ``held: True``."""
        flags = {k: info[k].cpu().numpy() for k in ("success", "collision", "out_of_bounds", "lost", "swapped")}
        cut = truncated.cpu().numpy()
        done = (terminated | truncated).cpu().numpy()
        infos: list[dict[str, Any]] = list(map(dict, itertools.repeat(_QUIET_INFO, len(done))))  # most rows: every flag False
        for i in np.flatnonzero(flags["success"] | flags["collision"] | flags["out_of_bounds"] | cut).tolist():
            infos[i].update({"is_success": bool(flags["success"][i]), "collision": bool(flags["collision"][i]),
                             "out_of_bounds": bool(flags["out_of_bounds"][i]), "TimeLimit.truncated": bool(cut[i])})
        held = info["held"].cpu().numpy()
        for i in np.flatnonzero(held).tolist():  # paused while its worker is replaced: reward 0, not done
            infos[i]["held"] = True
        if done.any():
            rows = np.flatnonzero(done)
            terminal = {k: v[rows] for k, v in self.to_numpy(info["terminal_observation"]).items()}  # done rows only
            ret = info["episode_return"].cpu().numpy()
            length = info["episode_length"].cpu().numpy()
            elapsed = round(time.time() - self._t0, 6)
            for j, i in enumerate(rows.tolist()):
                infos[i]["terminal_observation"] = {k: v[j] for k, v in terminal.items()}
                infos[i]["episode"] = {"r": float(ret[i]), "l": int(length[i]), "t": elapsed}
                infos[i]["lost"] = bool(flags["lost"][i])
                infos[i]["swapped"] = bool(flags["swapped"][i])
        return infos

    def to_numpy(self, obs: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
        """Observation tensors as numpy arrays of the observation space's dtypes."""
        return {k: obs[k].detach().cpu().numpy().astype(space.dtype, copy=False)
                for k, space in self.observation_space.spaces.items()}

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        """The attribute of this (single-process) env, once per index."""
        return [getattr(self, attr_name) for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        """Set an attribute; every agent shares this object, so ``indices`` cannot select some."""
        if len(list(self._get_indices(indices))) not in (0, self.num_envs):
            raise ConfigError(f"set_attr({attr_name!r}) applies to all {self.num_envs} agents at once; pass indices=None")
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any) -> list[Any]:
        """Call a method of this env once; its result is repeated per index."""
        result = getattr(self, method_name)(*method_args, **method_kwargs)
        return [result for _ in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        """Agents are not Gymnasium envs, so none is wrapped."""
        return [False for _ in self._get_indices(indices)]

    def _get_indices(self, indices: Any) -> Iterable[int]:
        if indices is None:
            return range(self.num_envs)
        out = [int(indices)] if isinstance(indices, (int, np.integer)) else [int(i) for i in indices]
        bad = [i for i in out if not -self.num_envs <= i < self.num_envs]
        if bad:
            raise IndexError(f"env indices {bad} out of range for num_envs={self.num_envs}")
        return out
