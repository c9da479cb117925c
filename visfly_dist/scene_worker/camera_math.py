"""Camera geometry shared by the renderers: quaternions, mounts, pixel rays.

Frames (docs/ARCHITECTURE.md): world z-up; body FLU; the camera frame of a mount is the body frame turned by the
mount rotation, so with the identity mount the optical axis is body +x, image "up" is body +z and
image "right" is body -y. A pixel ``(row i, column j)`` is sampled at its centre
``(j + 0.5, i + 0.5)``, row 0 at the top.
"""

from __future__ import annotations

import functools

import numpy as np

from visfly_dist.protocol.cameras import CameraSpec

CAMERA_TO_GL = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
"""Columns: the OpenGL camera axes (x right, y up, z backwards) in our camera frame."""


def quat_to_matrix(quat: np.ndarray) -> np.ndarray:
    """Rotation matrices of unit quaternions.

    Args:
        quat: ``(..., 4)`` quaternions ``wxyz`` (normalised here).

    Returns:
        ``(..., 3, 3)`` float64 matrices that rotate vectors from the local to the parent frame.
    """
    q = np.asarray(quat, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    m = np.empty(q.shape[:-1] + (3, 3))  # filled entry by entry: far cheaper than nested stacks for few drones
    m[..., 0, 0] = 1 - 2 * (y * y + z * z)
    m[..., 0, 1] = 2 * (x * y - w * z)
    m[..., 0, 2] = 2 * (x * z + w * y)
    m[..., 1, 0] = 2 * (x * y + w * z)
    m[..., 1, 1] = 1 - 2 * (x * x + z * z)
    m[..., 1, 2] = 2 * (y * z - w * x)
    m[..., 2, 0] = 2 * (x * z - w * y)
    m[..., 2, 1] = 2 * (y * z + w * x)
    m[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return m


@functools.lru_cache(maxsize=256)
def _mount_matrix(rotation: tuple[float, ...]) -> np.ndarray:
    return quat_to_matrix(np.asarray(rotation))


def camera_world_poses(poses: np.ndarray, camera: CameraSpec) -> tuple[np.ndarray, np.ndarray]:
    """World positions and orientations of one camera mounted on every drone.

    Args:
        poses: ``(n, 7)`` drone poses ``[x, y, z, qw, qx, qy, qz]`` (world).
        camera: the mount (``offset`` in the body frame, ``rotation`` body->camera).

    Returns:
        ``(origins (n, 3), rotations (n, 3, 3))``: camera centre and camera-to-world rotation.
    """
    body = quat_to_matrix(poses[:, 3:7])
    origins = poses[:, :3] + body @ np.asarray(camera.offset)
    return origins, body @ _mount_matrix(tuple(camera.rotation))


def pixel_slopes(camera: CameraSpec) -> tuple[np.ndarray, np.ndarray]:
    """Tangents of the pixel centres' angles off the optical axis.

    Returns:
        ``(right (W,), down (H,))`` float64: column ``j``'s ray goes ``right[j]`` towards image right
        (body -y) and row ``i``'s ray ``down[i]`` towards image bottom (body -z) per unit of depth.
    """
    f = camera.focal_px
    return ((np.arange(camera.width) + 0.5 - 0.5 * camera.width) / f,
            (np.arange(camera.height) + 0.5 - 0.5 * camera.height) / f)


def pixel_rays(camera: CameraSpec) -> np.ndarray:
    """Ray directions through every pixel centre, in the camera frame.

    Each direction has optical-axis component 1, so a ray parameter ``t`` is the z-depth of the point
    ``t * direction`` directly.

    Returns:
        ``(H * W, 3)`` float64, row-major over ``(row, column)``.
    """
    right, down = np.meshgrid(*pixel_slopes(camera))
    return np.stack([np.ones(right.size), -right.ravel(), -down.ravel()], axis=-1)


def spheres_in_view(camera: CameraSpec, centres: np.ndarray, radius: float) -> np.ndarray:
    """Whether spheres may show in the camera's image (conservative frustum test).

    Args:
        camera: intrinsics and clip planes.
        centres: ``(..., 3)`` sphere centres in the camera frame.
        radius: the spheres' radius.

    Returns:
        ``(...)`` bool: False only for spheres wholly outside the view frustum.
    """
    x, y, z = np.moveaxis(centres, -1, 0)
    sw, sh = 0.5 * camera.width / camera.focal_px, 0.5 * camera.height / camera.focal_px
    nw, nh = np.hypot(1.0, sw), np.hypot(1.0, sh)
    return ((x + radius > camera.near) & (x - radius < camera.far)
            & (sw * x - np.abs(y) >= -radius * nw) & (sh * x - np.abs(z) >= -radius * nh))


def gl_camera_pose(origin: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """The 4x4 world pose of an OpenGL-convention camera (looks along -z) at our camera's pose."""
    pose = np.eye(4)
    pose[:3, :3] = rotation @ CAMERA_TO_GL
    pose[:3, 3] = origin
    return pose
