"""Quaternion helpers on batched ``wxyz`` tensors of shape ``(..., 4)``.

Conventions: world z-up, body FLU, quaternion ``q`` rotates body vectors into the world frame.
Euler angles are ``(roll, pitch, yaw)`` in radians, applied as yaw about z, then pitch about the new
y, then roll about the new x (ZYX, intrinsic).
"""

from __future__ import annotations

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


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions ``(..., 4)`` (body to world)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack((
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ), dim=-1).reshape(q.shape[:-1] + (3, 3))


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
