"""Saving and loading a policy with its observation-normalisation statistics, without pickle.

A checkpoint is SB3's ``NAME.zip`` plus, when the run normalises observations, ``NAME.norm.npz``:
the running mean, variance and count of each normalised observation entry (``obs/KEY/mean`` ...),
of the return (``ret/...``), and the clip and epsilon settings. ``VecNormalize.save`` would pickle
the whole wrapper; plain arrays are enough to rebuild it around a fresh env.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Callable, Protocol

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

from visfly_dist.errors import ConfigError


def norm_path(checkpoint: Path) -> Path:
    """Where the normalisation statistics of ``checkpoint`` (``NAME.zip``) live: ``NAME.norm.npz``."""
    checkpoint = Path(checkpoint)
    return checkpoint.with_name(checkpoint.name.removesuffix(".zip") + ".norm.npz")


class Moments(Protocol):
    """Running statistics as ``RunningMeanStd`` keeps them."""

    @property
    def mean(self) -> Any: ...
    @property
    def var(self) -> Any: ...
    @property
    def count(self) -> float: ...


class NormalizationStatistics(Protocol):
    """What :func:`save_normalization` reads: a ``VecNormalize``, or the tensor PPO's statistics."""

    @property
    def clip_obs(self) -> float: ...
    @property
    def clip_reward(self) -> float: ...
    @property
    def epsilon(self) -> float: ...
    @property
    def gamma(self) -> float: ...
    @property
    def norm_reward(self) -> bool: ...
    @property
    def ret_rms(self) -> Moments: ...
    @property
    def obs_rms(self) -> Any: ...  # key -> Moments (a Dict observation space)


def save_normalization(venv: NormalizationStatistics, path: Path) -> None:
    """Write ``venv``'s running statistics to ``path`` (npz)."""
    arrays: dict[str, Any] = {  # arrays and numpy scalars (np.savez's stubs read a ** dict as its flags too)
        "clip_obs": np.float64(venv.clip_obs),
        "clip_reward": np.float64(venv.clip_reward),
        "epsilon": np.float64(venv.epsilon),
        "gamma": np.float64(venv.gamma),
        "norm_reward": np.bool_(venv.norm_reward),
        "ret/mean": np.asarray(venv.ret_rms.mean),
        "ret/var": np.asarray(venv.ret_rms.var),
        "ret/count": np.float64(venv.ret_rms.count),
    }
    for key, rms in venv.obs_rms.items():
        arrays[f"obs/{key}/mean"] = rms.mean
        arrays[f"obs/{key}/var"] = rms.var
        arrays[f"obs/{key}/count"] = np.float64(rms.count)
    with Path(path).open("wb") as f:
        np.savez(f, **arrays)


def load_normalization(venv: VecEnv, path: Path) -> VecNormalize:
    """Wrap ``venv`` in a frozen ``VecNormalize`` (``training=False``) with the statistics at ``path``."""
    with np.load(path, allow_pickle=False) as data:
        keys = sorted({name.split("/")[1] for name in data.files if name.startswith("obs/")})
        space = venv.observation_space
        observed = space.spaces if isinstance(space, spaces.Dict) else {}
        missing = [k for k in keys if k not in observed]
        if missing:
            raise ConfigError(f"normalisation file {path} has entries {missing} the env does not observe; is it from another task?")
        wrapped = VecNormalize(
            venv,
            training=False,
            norm_obs=bool(keys),
            norm_reward=bool(data["norm_reward"]),
            norm_obs_keys=keys or None,
            clip_obs=float(data["clip_obs"]),
            clip_reward=float(data["clip_reward"]),
            gamma=float(data["gamma"]),
            epsilon=float(data["epsilon"]),
        )
        for key in keys:
            rms = RunningMeanStd(shape=data[f"obs/{key}/mean"].shape)
            rms.mean, rms.var, rms.count = data[f"obs/{key}/mean"], data[f"obs/{key}/var"], float(data[f"obs/{key}/count"])
            wrapped.obs_rms[key] = rms
        wrapped.ret_rms.mean, wrapped.ret_rms.var = data["ret/mean"], data["ret/var"]
        wrapped.ret_rms.count = float(data["ret/count"])
    return wrapped


def save_on_crash(save: Callable[[Path], object], path: Path, steps: int) -> None:
    """Keep what a run learnt when an error ends it (no worker left, a scene that cannot serve):
    ``save(path)``, said on stderr. Called while the error propagates: a save that fails too is
    said and never hides it."""
    try:
        save(path)
    except Exception as exc:  # noqa: BLE001 -- the original error matters more than this one
        print(f"training stopped at {steps:,} steps by the error below; saving the model to {path} failed too ({exc})",
              file=sys.stderr, flush=True)
        return
    print(f"training stopped at {steps:,} steps by the error below; the model so far is in {path}",
          file=sys.stderr, flush=True)


def save_checkpoint(model: BaseAlgorithm, path: Path) -> Path:
    """Save the model to ``path`` (``.zip``) and, when its env is a VecNormalize, the statistics beside it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model.save(path)
    venv = model.get_env()
    if isinstance(venv, VecNormalize):
        save_normalization(venv, norm_path(path))
    return path


class Checkpoints:
    """``save(folder / "step_<n>.zip")`` each time ``n`` env steps reach ``every`` or more past the last
    save (``every=0``: never). Any trainer calls it with its step count; SB3's through :class:`CheckpointEvery`."""

    def __init__(self, folder: Path, every: int, save: Callable[[Path], Any]) -> None:
        self.folder, self.every, self.save = Path(folder), every, save
        self._next = every

    def __call__(self, num_timesteps: int) -> None:
        if self.every and num_timesteps >= self._next:
            self.save(self.folder / f"step_{num_timesteps}.zip")
            self._next = (num_timesteps // self.every + 1) * self.every


class CheckpointEvery(BaseCallback):
    """Saves ``checkpoints/step_<timesteps>.zip`` (and statistics) every ``every`` env steps of SB3's loop."""

    def __init__(self, folder: Path, every: int) -> None:
        super().__init__()
        self.checkpoints = Checkpoints(folder, every, lambda path: save_checkpoint(self.model, path))

    def _on_step(self) -> bool:
        self.checkpoints(self.num_timesteps)
        return True
