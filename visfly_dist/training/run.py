"""The plumbing every trainer shares: the env's keyword arguments, the run folder's config, the result.

Shared by the SB3 loop (``ppo``), the tensor PPO (``tensor_ppo``), BPTT/SHAC, evaluation, export and
the training video; it imports none of them, so each trainer reads top to bottom on it and none
needs another (no import cycle through ``ppo``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces

from visfly_dist.aggregator.config import PoolConfig
from visfly_dist.errors import ConfigError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.tasks import task_class
from visfly_dist.training.config import TrainConfig


def env_kwargs(cfg: TrainConfig, worker_logs: Path | None = None) -> dict[str, Any]:
    """Keyword arguments of ``make_env`` for this run: seed, ``--set`` overrides, pool settings.

    ``--set`` values arrive as JSON: ``cameras`` entries given as maps become ``CameraSpec``s, and
    a ``pool`` map changes fields of the task's default ``PoolConfig`` (as ``--workers`` etc. do).
    ``worker_logs``: where local workers write their logs, kept (a training run's ``workers/``),
    unless ``--set pool=...`` names a ``log_dir`` of its own.

    Raises:
        ConfigError: unknown task or pool field.
    """
    overrides = dict(cfg.overrides)
    pool_changes = overrides.pop("pool", {}) or {}
    if not isinstance(pool_changes, dict):
        raise ConfigError(f"--set pool={pool_changes!r} must be a JSON map of PoolConfig fields, e.g. pool={{\"lease_ms\":5000}}")
    flags = {"num_local_workers": cfg.workers, "worker_threads": cfg.worker_threads,
             "connect": tuple(cfg.connect) or None, "run_id": cfg.run_id,
             "backend": cfg.backend, "scene_roots": tuple(cfg.scene_roots) or None}
    pool_changes.update({k: v for k, v in flags.items() if v is not None})
    if worker_logs is not None:
        pool_changes.setdefault("log_dir", str(worker_logs))
    kwargs: dict[str, Any] = {"seed": cfg.seed, **overrides}
    if isinstance(kwargs.get("cameras"), list):
        kwargs["cameras"] = tuple(CameraSpec.from_dict(c) if isinstance(c, dict) else c for c in kwargs["cameras"])
    if pool_changes:
        default_pool = task_class(cfg.task).config_class().pool
        unknown = sorted(set(pool_changes) - set(PoolConfig.__dataclass_fields__))
        if unknown:
            raise ConfigError(f"unknown pool setting(s) {unknown}; valid: {sorted(PoolConfig.__dataclass_fields__)}")
        kwargs["pool"] = replace(default_pool, **pool_changes)
    return kwargs


def vector_keys(space: spaces.Dict) -> list[str]:
    """Float entries that are not images: the ones VecNormalize normalises."""
    return [k for k, s in space.spaces.items() if isinstance(s, spaces.Box) and len(s.shape) < 3 and np.issubdtype(s.dtype, np.floating)]


@dataclass
class TrainResult:
    """What a finished (or interrupted) run produced."""

    run_dir: Path
    final_model: Path
    timesteps: int
    interrupted: bool
    summary: dict[str, float]
    config: TrainConfig | None = None
    """The resolved configuration the run trained with (host plan included)."""


def write_config(cfg: TrainConfig, run_dir: Path) -> None:
    """Print the full config and save it as ``config.json``."""
    text = json.dumps(cfg.to_dict(), indent=2, default=str)
    print(f"visfly-dist train {cfg.task}: run folder {run_dir}\n{text}", flush=True)
    (run_dir / "config.json").write_text(text + "\n")
