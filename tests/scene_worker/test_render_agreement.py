"""The two backends agree on random poses in a generated scene (away from depth discontinuities)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import maximum_filter, minimum_filter

from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.scene_worker.render_base import available_backends, make_renderer
from visfly_dist.scenes import generate_scene

pytestmark = pytest.mark.skipif(set(available_backends()) != {"raycast", "egl"}, reason="needs both backends")


def random_poses(scene, n: int, rng: np.random.Generator) -> np.ndarray:
    low, high = scene.bounds
    pos = rng.uniform(low + [1.0, 1.0, 0.5], high - [1.0, 1.0, 0.5], size=(n, 3))
    quat = rng.normal(size=(n, 4)) * [1.0, 0.15, 0.15, 1.0]      # mostly yaw, some roll and pitch
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    return np.concatenate([pos, quat], axis=1)


def non_edge(depth: np.ndarray, seg: np.ndarray) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood shows one object and no depth jump above 10%."""
    size = (1, 3, 3)
    one_object = maximum_filter(seg, size) == minimum_filter(seg, size)
    smooth = maximum_filter(depth, size) - minimum_filter(depth, size) < 0.1 * depth
    return one_object & smooth


def test_raycast_and_egl_agree_on_garage_stones_with_drones():
    scene = generate_scene("garage-stones", seed=0)
    cams = [CameraSpec("d", "depth", 48, 36), CameraSpec("s", "segmentation", 48, 36)]
    poses = random_poses(scene, 24, np.random.default_rng(7))
    poses[1, :3] = poses[0, :3] + [0.8, 0.0, 0.0]     # a drone right in front of another one's view
    poses[1, 3:] = poses[0, 3:] = [1.0, 0.0, 0.0, 0.0]
    out = {}
    for backend in ("raycast", "egl"):
        with make_renderer(backend, scene, cams, drone_radius=0.1) as r:
            out[backend] = r.render(poses, show_drones=True)
    d_ray, d_egl = out["raycast"]["d"][:, 0], out["egl"]["d"][:, 0]
    s_ray, s_egl = out["raycast"]["s"][:, 0], out["egl"]["s"][:, 0]
    mask = non_edge(d_ray, s_ray) & non_edge(d_egl, s_egl)
    assert mask.mean() > 0.2
    diff = np.abs(d_ray - d_egl)[mask]
    assert np.median(diff) < 1e-3
    assert np.percentile(diff, 99) < 5e-3
    assert (s_ray == s_egl)[mask].mean() > 0.98
    assert (s_ray == s_egl).mean() > 0.95
    assert (s_ray[0] == 65534).sum() > 20 and (s_egl[0] == 65534).sum() > 20   # drone 1 seen by drone 0
