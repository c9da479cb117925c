"""Checks of what callers hand the aggregator: its settings, agent indices and poses (pure).

Every problem is a :class:`~visfly_dist.errors.ConfigError` naming what was wrong, raised before
anything is sent to a worker.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from visfly_dist.errors import ConfigError
from visfly_dist.protocol.cameras import CameraSpec

__all__ = ["agent_index", "increasing", "pose_rows", "setting_problems"]


def setting_problems(cameras: Sequence[CameraSpec], drone_radius: float, search_radius: float) -> list[str]:
    """The problems with the aggregator's own settings (empty when valid)."""
    problems = []
    if not cameras or not all(isinstance(c, CameraSpec) for c in cameras):
        problems.append(f"cameras={tuple(cameras)!r} must be a non-empty sequence of CameraSpec")
    elif len({c.name for c in cameras}) != len(cameras):
        problems.append(f"camera names {[c.name for c in cameras]} must be unique")
    if not 0 <= float(drone_radius) <= 10:
        problems.append(f"drone_radius={drone_radius!r} must be in [0, 10] m")
    if not 0 < float(search_radius) <= 1e4:
        problems.append(f"search_radius={search_radius!r} must be in (0, 1e4] m")
    return problems


def agent_index(agents: np.ndarray | Sequence[int] | None, num_agents: int) -> np.ndarray:
    """``agents`` (indices, a ``(num_agents,)`` bool mask, or ``None`` for all) as int64 indices."""
    if agents is None:
        return np.arange(num_agents, dtype=np.int64)
    if type(agents) is np.ndarray and agents.dtype == np.int64 and agents.ndim == 1:  # what the env passes
        idx = agents.copy()
        if idx.size and (idx.min() < 0 or idx.max() >= num_agents):
            raise ConfigError(f"agent indices must be in [0, {num_agents}), got {idx.min()}..{idx.max()}")
        return idx
    idx = np.asarray(agents)
    if idx.dtype == bool:
        if idx.shape != (num_agents,):
            raise ConfigError(f"agent mask of shape {idx.shape} must be ({num_agents},)")
        return np.flatnonzero(idx)
    if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer) and idx.size:
        raise ConfigError(f"agents must be a 1-D array of agent indices, got shape {idx.shape} dtype {idx.dtype}")
    idx = idx.astype(np.int64)
    if idx.size and (idx.min() < 0 or idx.max() >= num_agents):
        raise ConfigError(f"agent indices must be in [0, {num_agents}), got {idx.min()}..{idx.max()}")
    return idx


def pose_rows(poses: np.ndarray, agents: np.ndarray, num_agents: int) -> np.ndarray:
    """The ``(k, 7)`` float32 poses of ``agents`` from ``poses`` (all agents' rows or theirs only);
    finite, quaternions normalised."""
    poses = np.asarray(poses)
    if poses.ndim != 2 or poses.shape[1] != 7 or poses.shape[0] not in (num_agents, len(agents)):
        raise ConfigError(f"poses of shape {poses.shape} must be ({num_agents}, 7) or ({len(agents)}, 7): "
                          "rows [x, y, z, qw, qx, qy, qz]")
    rows = poses[agents] if poses.shape[0] == num_agents and len(agents) != num_agents else poses
    rows = np.asarray(rows, dtype=np.float32)
    if not len(rows):
        return rows
    if not math.isfinite(rows.sum()):  # a sum that overflowed is finite row by row: checked below
        finite = np.isfinite(rows).all(axis=1)
        if not finite.all():
            raise ConfigError(f"poses of agents {agents[np.flatnonzero(~finite)][:10].tolist()} are not finite")
    quats = rows[:, 3:]
    norms2 = np.einsum("ij,ij->i", quats, quats)
    # sqrt is monotonic: the extreme norms, exactly; as Python floats, whose differences from 1 are the
    # float32 ones (exact near 1), and no float32 lies between float32(1e-4) and 1e-4
    low, high = float(np.sqrt(norms2.min())), float(np.sqrt(norms2.max()))
    if low < 1e-6:
        raise ConfigError("poses hold a zero quaternion; quaternions are wxyz and must be unit")
    if high - 1 > 1e-4 or 1 - low > 1e-4:  # the largest |norm - 1|
        rows = rows.copy()
        rows[:, 3:] /= np.sqrt(norms2)[:, None]
    return rows


def increasing(agents: np.ndarray) -> bool:
    """Whether ``agents`` are in strictly increasing order (then each scene's rows are one run)."""
    return len(agents) < 2 or bool((agents[1:] > agents[:-1]).all())
