"""Evaluation videos: what the agent sees beside a chase camera that follows it.

Each frame is the agent's camera image (depth as grey levels, near = bright; RGB as is) next to a
third-person view rendered in this process with the ``raycast`` renderer from a camera ``distance``
metres behind and ``height`` metres above the drone (along the drone's yaw, kept inside the scene's
bounds), looking at it; the drone is drawn as a dark sphere. The scene is rebuilt in-process from the source the
agent's scene slot was loaded from (``gen:`` spec or a path under the pool's scene roots).

    recorder = VideoRecorder(env.unwrapped, agent=0)
    recorder.add(obs)            # once per observation the agent acts on
    recorder.save("eval.gif")
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.scene_worker.render_base import make_renderer
from visfly_dist.scenes import resolve_source
from visfly_dist.scenes.scene import Scene

PANEL = 192
"""Side of each square panel of a frame, pixels."""


def look_at_pose(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Pose ``[x, y, z, qw, qx, qy, qz]`` of a camera at ``eye`` whose optical axis points at ``target``."""
    d = np.asarray(target, np.float64) - np.asarray(eye, np.float64)
    yaw = math.atan2(d[1], d[0])
    pitch = math.atan2(-d[2], math.hypot(d[0], d[1]))  # positive looks down
    cy, sy, cp, sp = math.cos(yaw / 2), math.sin(yaw / 2), math.cos(pitch / 2), math.sin(pitch / 2)
    # q_yaw (about z) * q_pitch (about y)
    return np.array([*eye, cy * cp, -sy * sp, cy * sp, sy * cp])


def chase_pose(pos: np.ndarray, quat: np.ndarray, distance: float, height: float,
               bounds: np.ndarray | None = None, margin: float = 0.3) -> np.ndarray:
    """Pose of a camera ``distance`` behind (along the drone's yaw) and ``height`` above ``pos``, looking at it.

    With ``bounds`` (``(2, 3)``), the camera is kept ``margin`` inside them (so it stays inside a
    walled scene), coming closer to the drone when it would leave.
    """
    w, x, y, z = (float(c) for c in quat)
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    pos = np.asarray(pos, np.float64)
    eye = pos + np.array([-distance * math.cos(yaw), -distance * math.sin(yaw), height])
    if bounds is not None:
        eye = np.clip(eye, bounds[0] + margin, np.maximum(bounds[1] - margin, bounds[0] + margin))
    if np.linalg.norm(eye - pos) < 0.2:
        eye = pos + np.array([0.0, 0.0, max(height, 0.2)])
        return np.array([*eye, math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0])  # straight down
    return look_at_pose(eye, pos)


class ChaseCamera:
    """Renders the third-person view of one drone in a scene (raycast backend, in-process).

    Args:
        scene: the scene the drone flies in.
        size: image side, pixels.
        distance: metres behind the drone.
        height: metres above the drone.
        hfov_deg: horizontal field of view.
        drone_radius: radius of the sphere the drone is drawn as (larger than life, to be seen).
    """

    def __init__(self, scene: Scene, size: int = PANEL, distance: float = 2.0, height: float = 1.0,
                 hfov_deg: float = 80.0, drone_radius: float = 0.15) -> None:
        self.spec = CameraSpec(name="chase", kind="rgb", width=size, height=size, hfov_deg=hfov_deg, far=100.0)
        self.distance = distance
        self.height = height
        self.bounds = np.asarray(scene.bounds, np.float64)
        self.renderer = make_renderer("raycast", scene, [self.spec], drone_radius=drone_radius, threads=1)

    def render(self, pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
        """``(size, size, 3)`` uint8 view of the drone at ``pos`` with orientation ``quat`` (wxyz)."""
        drone = np.array([*pos, *quat], np.float64)
        poses = np.stack([chase_pose(pos, quat, self.distance, self.height, self.bounds), drone])
        image = self.renderer.render(poses, show_drones=True)["chase"][0]
        return np.ascontiguousarray(image.transpose(1, 2, 0))

    def close(self) -> None:
        self.renderer.close()


def observation_panel(image: np.ndarray, spec: CameraSpec, size: int = PANEL) -> np.ndarray:
    """The agent's ``(C, H, W)`` image as a ``(size, size, 3)`` uint8 panel (nearest-neighbour scaled).

    Depth: ``255 * (1 - d / far)`` grey (near = bright); RGB as is; segmentation: ids hashed to colours.
    """
    if spec.kind == "depth":
        grey = (255.0 * (1.0 - np.clip(image[0] / spec.far, 0.0, 1.0))).astype(np.uint8)
        rgb = np.repeat(grey[..., None], 3, axis=2)
    elif spec.kind == "rgb":
        rgb = np.asarray(image, np.uint8).transpose(1, 2, 0)
    else:
        ids = np.asarray(image[0], np.uint32)
        rgb = np.stack([(ids * 67) % 256, (ids * 151) % 256, (ids * 223) % 256], axis=2).astype(np.uint8)
    rows = np.arange(size) * rgb.shape[0] // size
    cols = np.arange(size) * rgb.shape[1] // size
    return rgb[rows][:, cols]


def label(panel: np.ndarray, text: str) -> np.ndarray:
    """``panel`` with ``text`` written in its top-left corner."""
    img = Image.fromarray(panel)
    draw = ImageDraw.Draw(img)
    draw.rectangle((0, 0, 6 * len(text) + 6, 13), fill=(0, 0, 0))
    draw.text((3, 1), text, fill=(255, 255, 255))
    return np.asarray(img)


def gif_duration_ms(fps: float) -> int:
    """Frame duration for imageio's GIF writer, which takes milliseconds.

    GIF stores whole centiseconds and Pillow truncates, so ``1000 / fps`` is rounded to the nearest
    10 ms (``1000 / (1 / 0.03)`` is 29.999... and would become 20 ms); at least 20 ms, because
    browsers play shorter delays at 100 ms.
    """
    if not fps > 0:
        raise ValueError(f"fps={fps!r} must be > 0")
    return max(20, 10 * round(100.0 / fps))


class VideoRecorder:
    """Collects frames of one agent of a :class:`~visfly_dist.client.env_base.DroneEnvBase`.

    Args:
        env: the unwrapped env (``vec_env.unwrapped``).
        agent: index of the agent filmed.
    """

    def __init__(self, env: Any, agent: int = 0) -> None:
        self.env = env
        self.agent = agent
        self.frames: list[np.ndarray] = []
        self.camera: CameraSpec | None = env.cameras[0] if env.cameras else None
        self._chase: ChaseCamera | None = None
        self._source: str | None = None

    def _chase_camera(self) -> ChaseCamera:
        source = self.env.aggregator.agent_sources()[self.agent]
        chase = self._chase
        if chase is None or source != self._source:
            if chase is not None:
                chase.close()
            chase = self._chase = ChaseCamera(resolve_source(source, self.env.config.pool.scene_roots))
            self._source = source
        return chase

    def add(self, obs: dict[str, np.ndarray], text: str = "") -> None:
        """Append a frame for the observation ``obs`` (all agents' rows) and the env's current state."""
        state = self.env.state
        pos = state.pos[self.agent].detach().cpu().numpy()
        quat = state.quat[self.agent].detach().cpu().numpy()
        chase = self._chase_camera().render(pos, quat)
        panels = [label(chase, text) if text else chase]
        if self.camera is not None:
            panels.insert(0, label(observation_panel(obs[self.camera.name][self.agent], self.camera), self.camera.name))
        self.frames.append(np.concatenate(panels, axis=1))

    def save(self, path: str | Path, fps: float | None = None) -> Path:
        """Write the frames as a GIF (or any format imageio knows by the suffix).

        Args:
            path: output file.
            fps: frames per second; default: the env's control rate (``1 / ctrl_dt``), so the video
                plays in real time.
        """
        import imageio.v2 as imageio

        if not self.frames:
            raise ValueError("no frames to save: call add() once per observation before save()")
        fps = 1.0 / float(self.env.config.ctrl_dt) if fps is None else float(fps)
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        imageio.mimsave(path, list(self.frames), duration=gif_duration_ms(fps), loop=0)
        return path

    def close(self) -> None:
        if self._chase is not None:
            self._chase.close()
            self._chase = None
