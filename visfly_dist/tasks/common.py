"""Small pieces the tasks share: frames, goal geometry and reward terms (all batched torch)."""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
import torch

from visfly_dist.dynamics.rotations import quat_to_rotmat
from visfly_dist.errors import ConfigError

if TYPE_CHECKING:
    from visfly_dist.client.frame import SensorFrame

TARGET_DIM = 4
"""``target_observation``: unit direction to the target in the body frame, distance (m)."""


def sensed(frame: SensorFrame | None) -> SensorFrame:
    """The env's last sensor frame, ``frame``: the env calls a task's hooks only once it has one."""
    assert frame is not None, "a task hook ran before the env's first observation"
    return frame


def to_body(quat: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """World vectors ``(N, 3)`` in each agent's body frame (``quat`` rotates body to world)."""
    return body_from_rotmat(quat_to_rotmat(quat), v)


def body_from_rotmat(rotmat: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """World vectors ``(N, 3)`` in the body frames of the rotations ``rotmat`` ``(N, 3, 3)`` (``R^T v``)."""
    return (v.unsqueeze(-2) @ rotmat).squeeze(-2)


def forward_axis(quat: torch.Tensor) -> torch.Tensor:
    """``(N, 3)`` the body +x axis in the world frame."""
    return quat_to_rotmat(quat)[..., 0]


def target_observation(pos: torch.Tensor, quat: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``(N, 4)``: unit direction from ``pos`` to ``target`` in the body frame, then the distance (m)."""
    delta = target - pos
    dist = delta.norm(dim=1, keepdim=True)
    return torch.cat((to_body(quat, delta / dist.clamp(min=1e-6)), dist), dim=1)


def weighted_sum(terms: Sequence[torch.Tensor], weights: tuple[float, ...]) -> torch.Tensor:
    """``(N,)`` ``sum_k weights[k] * terms[k]`` of ``(N,)`` terms, as one matrix-vector product (one
    op, not two per term; the weights' tensor is made once per weights, dtype and device)."""
    stacked = torch.stack(tuple(terms), dim=1)
    return stacked @ _constant(weights, stacked.dtype, stacked.device)


@functools.lru_cache(maxsize=64)
def _constant(values: tuple[float, ...], dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """A tensor of ``values`` made once: never write into it."""
    return torch.tensor(values, dtype=dtype, device=device)


def progress_speed(prev_distance: torch.Tensor, distance: torch.Tensor, dt: float) -> torch.Tensor:
    """``(N,)`` speed of approach to a target, m/s (positive when getting closer)."""
    return (prev_distance - distance) / dt


def obstacle_terms(pos: torch.Tensor, vel: torch.Tensor, nearest: torch.Tensor, distance: torch.Tensor,
                   search_radius: float, near: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Obstacle proximity ``1 / (d + 0.2)`` and approach speed toward the nearest obstacle (when ``d < near``).

    ``d`` is the distance from the drone's centre to the nearest obstacle point; both terms are 0 where
    no obstacle lies within ``search_radius``. The approach speed (m/s, positive toward the obstacle)
    carries gradients through ``vel`` and ``pos``.
    """
    seen = distance < search_radius * 0.999
    delta = nearest - pos
    d = delta.norm(dim=1)
    direction = delta / d.clamp(min=1e-6)[:, None]
    approach = (vel * direction).sum(dim=1).clamp(min=0.0)
    return (d + 0.2).reciprocal() * seen, approach * (seen & (d < near))


def metadata_point(meta: dict[str, Any], key: str, default: Sequence[float]) -> np.ndarray:
    """A 3-vector from scene metadata, or ``default`` when the scene has none."""
    value = meta.get(key, default)
    try:
        point = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):  # not numbers, or ragged
        point = np.zeros(0)
    if point.shape != (3,) or not np.all(np.isfinite(point)):
        raise ConfigError(f"scene metadata {key}={value!r} must be 3 finite numbers")
    return point


def metadata_points(metas: Sequence[dict[str, Any]], key: str, default: Sequence[float]) -> np.ndarray:
    """``(k, 3)`` float64: :func:`metadata_point` of each of ``metas``, converted and checked at once."""
    values = [meta.get(key, default) for meta in metas]
    try:
        points = np.asarray(values, dtype=np.float64).reshape(len(values), -1)
    except (TypeError, ValueError):  # ragged or not numbers: the one-by-one check names the culprit
        points = np.zeros((len(values), 0))
    if points.shape[1] != 3 or not np.isfinite(points).all():
        return np.array([metadata_point(meta, key, default) for meta in metas]).reshape(-1, 3)
    return points


def vec3_problem(name: str, value: Any, positive: bool = False) -> list[str]:
    """A problem message when ``value`` is not 3 finite numbers (``> 0`` each with ``positive``)."""
    try:
        v = [float(x) for x in value]
    except (TypeError, ValueError):
        return [f"{name}={value!r} must be 3 numbers"]
    if len(v) != 3 or not all(math.isfinite(x) for x in v) or (positive and min(v) < 0):
        return [f"{name}={value!r} must be 3 finite numbers" + (" >= 0" if positive else "")]
    return []


REWARDS = ("ours", "visfly")
"""Reward variants a task offers: ``ours`` (the default) and ``visfly`` (the original's, term by term)."""


def reward_problem(value: Any) -> list[str]:
    """A problem message when ``value`` is not one of :data:`REWARDS`."""
    return [] if value in REWARDS else [f"reward={value!r} must be one of {list(REWARDS)}"]


def approach_speed(pos: torch.Tensor, vel: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``(N,)`` velocity component toward ``target``, m/s (positive when closing in); differentiable."""
    delta = target - pos
    return (vel * delta).sum(dim=1) / (delta.norm(dim=1) + 1e-6)


def angle_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``(N,)`` angle between the rows of ``a`` and ``b``, radians in ``[0, pi]``."""
    cos = (a * b).sum(dim=1) / (a.norm(dim=1) * b.norm(dim=1) + 1e-6)
    return cos.clamp(-1.0, 1.0).acos()


def attitude_error(quat: torch.Tensor) -> torch.Tensor:
    """``(N,)`` ``|q - (1, 0, 0, 0)|``: VisFly's (tiny-weighted) attitude penalty term."""
    level = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quat.dtype, device=quat.device)
    return (quat - level).norm(dim=1)


def held_steps(held: torch.Tensor, inside: torch.Tensor) -> torch.Tensor:
    """``(N,)`` consecutive steps inside a region, counting this one: ``held + 1`` where ``inside``, else 0."""
    return torch.where(inside, held + 1, torch.zeros_like(held))


def visfly_hover_reward(quat: torch.Tensor, vel: torch.Tensor, omega: torch.Tensor, distance: torch.Tensor) -> torch.Tensor:
    """``(N,)`` VisFly's hover/tracking reward: 0.1 at the target, falling with distance, small
    attitude, speed and spin penalties."""
    return 0.1 - 0.1 / 9 * distance - 1e-5 * attitude_error(quat) - 0.002 * vel.norm(dim=1) - 0.002 * omega.norm(dim=1)
