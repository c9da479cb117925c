"""Quaternion helpers on batched ``wxyz`` tensors of shape ``(..., 4)``.

Conventions: world z-up, body FLU, quaternion ``q`` rotates body vectors into the world frame.
Euler angles are ``(roll, pitch, yaw)`` in radians, applied as yaw about z, then pitch about the new
y, then roll about the new x (ZYX, intrinsic).
"""

from __future__ import annotations

import functools

import torch


def quat_multiply(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``p * q`` of ``(..., 4)`` quaternions."""
    pw, px, py, pz = p.unbind(-1)
    qw, qx, qy, qz = q.unbind(-1)
    return torch.stack((
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ), dim=-1)


# Entry k of the row-major matrix is COEF[k] q_a q_b + COEF[9 + k] q_c q_d (+ 1 on the diagonal), with
# (a, b) = (LEFT[k], RIGHT[k]) and (c, d) = (LEFT[9 + k], RIGHT[9 + k]); every coefficient is +-2.
_W, _X, _Y, _Z = range(4)
_LEFT = (_Y, _X, _X, _X, _X, _Y, _X, _Y, _X, _Z, _W, _W, _W, _Z, _W, _W, _W, _Y)
_RIGHT = (_Y, _Y, _Z, _Y, _X, _Z, _Z, _Z, _X, _Z, _Z, _Y, _Z, _Z, _X, _Y, _X, _Y)
_COEF = (-2.0, 2.0, 2.0, 2.0, -2.0, 2.0, 2.0, 2.0, -2.0, -2.0, -2.0, 2.0, 2.0, -2.0, -2.0, -2.0, 2.0, -2.0)
_EYE = (1.0, -0.0, -0.0, -0.0, 1.0, -0.0, -0.0, -0.0, 1.0)  # x + (-0) is x bit for bit, -0 included


@functools.lru_cache(maxsize=16)
def _rotmat_tables(dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    index = torch.tensor(_LEFT + _RIGHT, dtype=torch.long, device=device)
    coef = torch.tensor(_COEF, dtype=dtype, device=device)[:, None]
    return index, coef, torch.tensor(_EYE, dtype=dtype, device=device)[:, None]


def rotmat_rows(q_columns: torch.Tensor) -> torch.Tensor:
    """``(9, M)`` row-major rotation matrix entries of the unit quaternions in the columns of ``(4, M)``.

    Component-major on purpose: every operation runs on whole contiguous rows, several times cheaper
    for a few hundred agents than on ``(M, 3, 3)`` blocks with broadcast inner dimensions (the task
    hooks call this every step). The values are bit for bit the textbook entries ``1 - 2 (y^2 + z^2)``,
    ``2 (x y - w z)``, ...: ``q_a (2 q_b)`` is ``2 (q_a q_b)`` exactly, ``1 - 2 s`` is ``1 + (-2) s``
    and ``a - b`` is ``a + (-1) b`` in IEEE arithmetic (barring subnormal products).
    """
    index, coef, eye = _rotmat_tables(q_columns.dtype, q_columns.device)
    factors = q_columns.index_select(0, index)  # the left factors of the 18 products, then the right ones
    products = factors[:18] * (factors[18:] * coef)
    return (products[:9] + products[9:]).add_(eye)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions ``(..., 4)`` (body to world), bit for bit
    the textbook entries (see :func:`rotmat_rows`)."""
    rows = rotmat_rows(q.reshape(-1, 4).t())
    return rows.t().reshape(q.shape[:-1] + (3, 3)).contiguous()


def rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate body vectors ``v (..., 3)`` into the world frame by quaternions ``q (..., 4)``."""
    return (quat_to_rotmat(q) @ v.unsqueeze(-1)).squeeze(-1)


def quat_from_euler(euler: torch.Tensor) -> torch.Tensor:
    """Unit quaternions ``(..., 4)`` from ``(roll, pitch, yaw)`` angles ``(..., 3)`` in radians."""
    half = 0.5 * euler
    cr, cp, cy = half.cos().unbind(-1)
    sr, sp, sy = half.sin().unbind(-1)
    return torch.stack((
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ), dim=-1)


def euler_from_quat(q: torch.Tensor) -> torch.Tensor:
    """``(roll, pitch, yaw)`` in radians ``(..., 3)`` of unit quaternions ``(..., 4)``."""
    w, x, y, z = q.unbind(-1)
    roll = torch.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = torch.asin((2 * (w * y - z * x)).clamp(-1.0, 1.0))
    yaw = torch.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return torch.stack((roll, pitch, yaw), dim=-1)


def quat_from_rotvec(rotvec: torch.Tensor) -> torch.Tensor:
    """Unit quaternions ``(..., 4)`` of rotation vectors ``(..., 3)`` (axis times angle, radians)."""
    angle = rotvec.norm(dim=-1, keepdim=True)
    half = 0.5 * angle
    # sin(a/2)/a -> 1/2 as a -> 0; the series keeps small angles exact and finite.
    small = angle < 1e-6
    scale = torch.where(small, 0.5 - angle * angle / 48.0, half.sin() / angle.where(~small, torch.ones_like(angle)))
    return torch.cat((half.cos(), rotvec * scale), dim=-1)
