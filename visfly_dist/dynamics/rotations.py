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


# Entry k of the row-major matrix is SCALE[k] * (q_a q_b + SIGN[k] q_c q_d) (+ 1 on the diagonal),
# with (a, b) = FIRST[k] and (c, d) = SECOND[k] as flat indices 4 a + b into the outer product q q^T.
_W, _X, _Y, _Z = range(4)
_FIRST = (4 * _Y + _Y, 4 * _X + _Y, 4 * _X + _Z, 4 * _X + _Y, 4 * _X + _X, 4 * _Y + _Z, 4 * _X + _Z, 4 * _Y + _Z,
          4 * _X + _X)
_SECOND = (4 * _Z + _Z, 4 * _W + _Z, 4 * _W + _Y, 4 * _W + _Z, 4 * _Z + _Z, 4 * _W + _X, 4 * _W + _Y, 4 * _W + _X,
           4 * _Y + _Y)
_SIGN = (1.0, -1.0, 1.0, 1.0, 1.0, -1.0, -1.0, 1.0, 1.0)
_SCALE = (-2.0, 2.0, 2.0, 2.0, -2.0, 2.0, 2.0, 2.0, -2.0)


@functools.lru_cache(maxsize=16)
def _rotmat_tables(dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, ...]:
    def table(values: tuple, kind: torch.dtype) -> torch.Tensor:
        return torch.tensor(values, dtype=kind, device=device)

    return table(_FIRST, torch.long), table(_SECOND, torch.long), table(_SIGN, dtype), table(_SCALE, dtype)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions ``(..., 4)`` (body to world).

    The textbook entries, ``1 - 2 (y^2 + z^2)``, ``2 (x y - w z)``, ..., computed from the outer
    product ``q q^T`` in a few batched operations instead of some forty small ones (the task hooks
    call this every step). The values are bit for bit those of the entry-by-entry form:
    ``1 - 2 s`` is ``1 + (-2) s`` and ``a - b`` is ``a + (-1) b`` in IEEE arithmetic.
    """
    first, second, sign, scale = _rotmat_tables(q.dtype, q.device)
    products = (q[..., :, None] * q[..., None, :]).flatten(-2)
    out = scale * (products.index_select(-1, first) + sign * products.index_select(-1, second))
    out[..., ::4] += 1  # the diagonal, entries 0, 4 and 8
    return out.reshape(q.shape[:-1] + (3, 3))


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
