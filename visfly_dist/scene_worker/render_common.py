"""What every renderer backend shares: the :class:`Renderer` base class, the look of what has no
material (sky, drones, the light) and the drones' segmentation ids.

The backends (``render_raycast``, ``render_egl_batch``, ``render_egl_legacy``) and the shading
import this module; :mod:`visfly_dist.scene_worker.render_base` (the backend choice and
``make_renderer``) imports the backends. Nothing here imports a backend, so the imports point one
way: ``render_base -> backends -> render_common`` (see that module's docstring for the contract).
"""

from __future__ import annotations

import abc
from typing import Sequence, overload

import numpy as np

from visfly_dist.errors import ConfigError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.scenes.scene import Scene

DRONE_SEGMENTATION_MAX = 65535
SKY_RGB = (150, 180, 210)
DRONE_RGB = (40, 40, 40)
LIGHT_DIRECTION = tuple(np.array([0.4, 0.3, 0.85]) / np.linalg.norm([0.4, 0.3, 0.85]))
"""Unit vector from the scene towards the (directional) light, world frame."""
AMBIENT = 0.4
"""Share of a surface's colour lit regardless of the light; the rest scales with |n . light|."""


@overload
def drone_segmentation_id(agent_index: int) -> int: ...


@overload
def drone_segmentation_id(agent_index: np.ndarray) -> np.ndarray: ...


def drone_segmentation_id(agent_index: int | np.ndarray) -> int | np.ndarray:
    """Segmentation id of agent ``k`` of a render call: ``65535 - k``."""
    return DRONE_SEGMENTATION_MAX - agent_index


class Renderer(abc.ABC):
    """Renders the cameras of a batch of drones in one scene.

    Attributes:
        name: the backend, ``"egl"`` or ``"raycast"``.
        scene: the scene drawn.
        cameras: the cameras mounted on every drone.
        drone_radius: radius of the sphere a drone is drawn as, metres.
        moving: the scene's moving objects, in scene order.
    """

    name: str

    def __init__(self, scene: Scene, cameras: Sequence[CameraSpec], drone_radius: float) -> None:
        cameras = tuple(cameras)
        if not cameras:
            raise ConfigError("a renderer needs at least one CameraSpec; got none")
        names = [c.name for c in cameras]
        if len(set(names)) != len(names):
            raise ConfigError(f"camera names {names} must be unique")
        if not (np.isfinite(drone_radius) and drone_radius >= 0):
            raise ConfigError(f"drone_radius={drone_radius!r} must be a finite number >= 0")
        self.scene = scene
        self.cameras = cameras
        self.drone_radius = float(drone_radius)
        self._closed = False
        self._placed_at: float | None = None
        self.moving = tuple(scene.moving_objects)   # scene order; looked up once (it is a scan of the objects)
        self._motions = tuple(o.motion for o in self.moving if o.motion is not None)   # all of them: they move

    def render(self, poses: np.ndarray, show_drones: bool = False, time: float = 0.0) -> dict[str, np.ndarray]:
        """Render every camera of every drone.

        Args:
            poses: ``(n, 7)`` drone poses ``[x, y, z, qw, qx, qy, qz]`` in the world frame.
            show_drones: draw the other drones of this call (multi-agent scenes).
            time: simulation time, s: where the moving obstacles are drawn.

        Returns:
            ``{camera.name: (n, C, H, W) array of camera.dtype}``.
        """
        poses = self._checked_poses(poses, show_drones)
        if len(poses) == 0:
            return {c.name: np.zeros((0, *c.shape), c.dtype) for c in self.cameras}
        self.place(time)
        return self._render(poses, bool(show_drones))

    def place(self, time: float) -> None:
        """Put the moving obstacles where they are at ``time`` (s); nothing to do in a static scene."""
        time = checked_time(time)
        if self.moving and self._placed_at != time:
            self._move(np.stack([motion.position(time) for motion in self._motions]))
            self._placed_at = time

    def _move(self, translations: np.ndarray) -> None:
        """Backend work: place moving object ``k`` (scene order) at ``translations[k]`` ``(m, 3)``."""
        raise NotImplementedError(f"the {self.name} renderer does not draw moving obstacles")

    def _checked_poses(self, poses: np.ndarray, show_drones: bool) -> np.ndarray:
        """``poses`` as float64 ``(n, 7)``; ConfigError if they (or the renderer) can't be rendered."""
        if self._closed:
            raise ConfigError(f"this {self.name} renderer was closed; make a new one with make_renderer")
        poses = np.asarray(poses, dtype=np.float64)
        if poses.ndim != 2 or poses.shape[1] != 7:
            raise ConfigError(f"poses shape {poses.shape} must be (n, 7): x y z qw qx qy qz")
        if not np.all(np.isfinite(poses)):
            raise ConfigError("poses contain NaN or infinite values; pass finite poses")
        if np.any(np.linalg.norm(poses[:, 3:], axis=1) < 1e-9):
            raise ConfigError("poses contain a zero quaternion; pass unit quaternions wxyz")
        if show_drones and len(poses) and drone_segmentation_id(len(poses) - 1) <= self._max_object_id():
            raise ConfigError(f"{len(poses)} drones would share segmentation ids with scene objects "
                              f"(max object id {self._max_object_id()}); render fewer agents per call")
        return poses

    @abc.abstractmethod
    def _render(self, poses: np.ndarray, show_drones: bool) -> dict[str, np.ndarray]:
        """Backend work on validated, non-empty float64 poses."""

    def close(self) -> None:
        """Free the backend's resources; idempotent."""
        if not self._closed:
            self._closed = True
            self._release()

    def _release(self) -> None:  # noqa: B027 - an optional hook: a backend without resources keeps it
        """Backend clean-up, called once by :meth:`close`."""

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _max_object_id(self) -> int:
        return max((o.object_id for o in self.scene.objects), default=0)


def checked_time(time: object) -> float:
    """A simulation time as a float; ConfigError unless it is a finite number of seconds."""
    if isinstance(time, bool) or not isinstance(time, (int, float, np.floating, np.integer)) or not np.isfinite(time):
        raise ConfigError(f"time={time!r} must be a finite number of seconds")
    return float(time)
