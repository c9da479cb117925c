"""Video pieces: the chase camera's pose looks at the drone, and the drone shows in its image."""

from __future__ import annotations

import math

import numpy as np
import torch

from visfly_dist.dynamics.rotations import rotate
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.scenes import resolve_source
from visfly_dist.training.video import ChaseCamera, chase_pose, gif_duration_ms, observation_panel


def optical_axis(pose: np.ndarray) -> np.ndarray:
    q = torch.tensor(pose[3:], dtype=torch.float64)[None]
    return rotate(q, torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64))[0].numpy()


def test_chase_pose_sits_behind_and_above_and_looks_at_the_drone() -> None:
    pos = np.array([5.0, 1.0, 1.5])
    yaw = math.radians(30)
    quat = np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
    pose = chase_pose(pos, quat, distance=2.0, height=1.0)
    np.testing.assert_allclose(pose[:3], pos + [-2 * math.cos(yaw), -2 * math.sin(yaw), 1.0], atol=1e-12)
    to_drone = (pos - pose[:3]) / np.linalg.norm(pos - pose[:3])
    np.testing.assert_allclose(optical_axis(pose), to_drone, atol=1e-9)


def test_chase_pose_stays_inside_bounds() -> None:
    bounds = np.array([[0.0, -7.0, 0.0], [18.0, 7.0, 5.0]])
    pos = np.array([1.0, 0.0, 4.5])
    pose = chase_pose(pos, np.array([1.0, 0, 0, 0]), distance=2.0, height=1.0, bounds=bounds, margin=0.3)
    np.testing.assert_allclose(pose[:3], [0.3, 0.0, 4.7])
    to_drone = (pos - pose[:3]) / np.linalg.norm(pos - pose[:3])
    np.testing.assert_allclose(optical_axis(pose), to_drone, atol=1e-9)


def test_chase_camera_sees_the_drone_in_the_middle() -> None:
    scene = resolve_source("gen:empty", [])
    cam = ChaseCamera(scene, size=64)
    try:
        image = cam.render(np.array([2.0, 0.0, 1.5]), np.array([1.0, 0.0, 0.0, 0.0]))
    finally:
        cam.close()
    assert image.shape == (64, 64, 3) and image.dtype == np.uint8
    centre = image[30:34, 30:34].astype(int)
    assert centre.max() < 90  # the dark drone sphere
    assert image[2, 2].astype(int).sum() > 3 * 90  # sky or floor around it


def test_depth_panel_is_bright_near_and_scaled_up() -> None:
    spec = CameraSpec(width=2, height=2, far=20.0)
    panel = observation_panel(np.array([[[0.0, 10.0], [20.0, 30.0]]], np.float32), spec, size=4)
    assert panel.shape == (4, 4, 3)
    assert panel[0, 0, 0] == 255 and panel[0, 3, 0] == 127 and panel[3, 0, 0] == 0 and panel[3, 3, 0] == 0


def test_gif_frames_last_one_env_step_in_whole_centiseconds() -> None:
    assert gif_duration_ms(1 / 0.03) == 30  # 1000 / 33.33... is 29.99..., which GIF would truncate to 20
    assert gif_duration_ms(1 / 0.05) == 50
    assert gif_duration_ms(200) == 20  # browsers play shorter delays at 100 ms
