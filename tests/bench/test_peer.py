"""The pybullet peer: it runs, its physics holds a hover, and its depth matches ours on the same scene."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

pytest.importorskip("pybullet")

from visfly_dist.bench.peer import PeerCamera, peer_depth, peer_physics
from visfly_dist.errors import ConfigError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.scenes.scene import Scene, SceneObject


def wall_scene() -> Scene:
    """A 0.2 m thick wall whose near face is the plane x = 5."""
    wall = trimesh.creation.box((0.2, 10.0, 10.0))
    wall.apply_translation((5.1, 0.0, 0.0))
    return Scene("wall", [SceneObject("wall", 1, wall)], [[-1, -5, 0], [10, 5, 5]])


def test_peer_physics_tiny_gives_positive_figures_and_hovers():
    out = peer_physics(drones=4, seconds=0.25)
    assert out["drones"] == 4 and out["sim_seconds_per_s"] > 0 and out["agent_steps_per_s"] > 0
    # Rotor forces at hover +-5 % rpm: the drones neither fall nor fly off within a quarter second.
    assert abs(out["final_mean_z"] - 1.5) < 0.2


def test_peer_physics_rejects_bad_sizes():
    with pytest.raises(ConfigError, match="drones=0"):
        peer_physics(drones=0, seconds=1.0)


def test_peer_depth_is_metric_z_depth_of_a_plane():
    """A camera facing a wall 5 m away sees 5 m along the optical axis at every pixel; yawed, z-depth varies
    across columns as 5 / (cos(yaw) + tan(angle) sin(yaw)) at each pixel centre."""
    cam = CameraSpec(width=8, height=8, hfov_deg=60.0)
    yaw = 0.2
    poses = np.array([[0, 0, 1, 1, 0, 0, 0], [0, 0, 1, math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)]], dtype=float)
    with PeerCamera(wall_scene(), cam) as peer:
        depth = peer.depth(poses)
    assert depth.shape == (2, 1, 8, 8) and depth.dtype == np.float32
    np.testing.assert_allclose(depth[0], 5.0, atol=1e-3)
    # Column j looks at angle a_j to the right of the axis (body -y); the camera is yawed left by `yaw`.
    right = (np.arange(8) + 0.5 - 4.0) / cam.focal_px
    expected = 5.0 / (math.cos(yaw) + right * math.sin(yaw))
    np.testing.assert_allclose(depth[1, 0], np.broadcast_to(expected, (8, 8)), rtol=2e-3)


def test_peer_depth_agrees_with_our_raycast_on_garage_stones():
    """Same mesh, same poses: TinyRenderer's depth and our Embree depth agree at pixel centres."""
    pytest.importorskip("embreex")
    from visfly_dist.scene_worker.render_base import make_renderer
    from visfly_dist.scenes import generate_scene

    scene = generate_scene("garage-stones", seed=0)
    cam = CameraSpec(width=32, height=32)
    # Facing the far wall (x = 18) from 2-3 m, slightly pitched down so the floor shows in the lower rows,
    # and one looking sideways at the y = -7 wall.
    pitch = 0.15
    yaw = -math.pi / 2
    poses = np.array([
        [15.5, 1.0, 2.0, math.cos(pitch / 2), 0, math.sin(pitch / 2), 0],
        [16.0, -3.0, 3.0, 1, 0, 0, 0],
        [12.0, -4.5, 1.5, math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)],
    ])
    with PeerCamera(scene, cam) as peer:
        theirs = peer.depth(poses)
    with make_renderer("raycast", scene, [cam]) as ours_renderer:
        ours = ours_renderer.render(poses)["depth"]
    assert ours.shape == theirs.shape
    diff = np.abs(ours - theirs)
    assert np.median(diff) < 0.01, f"median |raycast - TinyRenderer| = {np.median(diff):.4f} m"
    assert np.mean(diff < 0.05) > 0.9, f"only {np.mean(diff < 0.05):.0%} of pixels agree within 5 cm"
    # The floor is in the lower rows of the pitched view in both (rows are not flipped).
    assert theirs[0, 0, -1].mean() < theirs[0, 0, 0].mean()


def test_peer_depth_frames_per_second_is_positive():
    out = peer_depth(res=16, cameras=3, scene=wall_scene(), reps=1)
    assert out["frames_per_s"] > 0 and out["cameras"] == 3 and out["res"] == 16 and out["triangles"] == 12
