"""Both render backends against analytic answers: depth at pixel centres, frames, ids, colours, drones."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from visfly_dist.errors import ConfigError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.scene_worker.render_base import (
    SKY_RGB, available_backends, choose_backend, drone_segmentation_id, make_renderer, resolve_backend,
)
from visfly_dist.scenes.scene import Scene, SceneObject

BACKENDS = [pytest.param(b, marks=pytest.mark.skipif(b not in available_backends(), reason=f"{b} unavailable"))
            for b in ("raycast", "egl")]
DEPTH_TOL = {"raycast": 1e-4, "egl": 1e-3}   # metres, at pixel centres
IDENTITY = np.array([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])


def box(extents, centre, colour=(128, 128, 128)) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents)
    mesh.apply_translation(centre)
    mesh.visual.face_colors = [*colour, 255]
    return mesh


def scene_of(*meshes: trimesh.Trimesh, ids=None) -> Scene:
    ids = ids or list(range(1, len(meshes) + 1))
    objects = [SceneObject(f"o{i}", i, m) for i, m in zip(ids, meshes)]
    return Scene("test", objects, np.array([[-50.0, -50.0, -50.0], [50.0, 50.0, 50.0]]))


def render(backend, scene, cameras, poses, show_drones=False):
    with make_renderer(backend, scene, cameras, drone_radius=0.1) as r:
        assert r.name == backend
        return r.render(poses, show_drones=show_drones)


def analytic_zdepth(camera: CameraSpec, cam_to_world: np.ndarray, plane_z: float, height: float) -> np.ndarray:
    """z-depth of the plane ``z = plane_z`` seen from a camera at height ``height``, per pixel centre."""
    f = 0.5 * camera.width / math.tan(math.radians(camera.hfov_deg) / 2)
    u = np.arange(camera.width) + 0.5
    v = np.arange(camera.height) + 0.5
    uu, vv = np.meshgrid(u, v)
    # camera frame: x optical axis, image right = -y, image up = +z
    rays = np.stack([np.ones_like(uu), -(uu - camera.width / 2) / f, -(vv - camera.height / 2) / f], axis=-1)
    down = rays @ cam_to_world.T
    with np.errstate(divide="ignore"):
        t = (plane_z - height) / down[..., 2]
    return np.where((t > camera.near) & (t < camera.far), t, camera.far)


@pytest.mark.parametrize("backend", BACKENDS)
def test_facing_wall_depth_is_exact_at_every_pixel(backend):
    wall = box((0.02, 40, 40), (3.01, 0, 0))
    cams = [CameraSpec("d", "depth", 17, 11, hfov_deg=100), CameraSpec("m", "depth", 8, 8, offset=(0.5, 0.2, -0.1))]
    out = render(backend, scene_of(wall), cams, IDENTITY)
    assert out["d"].shape == (1, 1, 11, 17) and out["d"].dtype == np.float32
    np.testing.assert_allclose(out["d"], 3.0, atol=DEPTH_TOL[backend])
    np.testing.assert_allclose(out["m"], 2.5, atol=DEPTH_TOL[backend])


@pytest.mark.parametrize("backend", BACKENDS)
def test_tilted_camera_matches_analytic_z_depth(backend):
    floor = box((200, 200, 0.02), (0, 0, -1.01))
    cam = CameraSpec("d", "depth", 40, 30, hfov_deg=80, far=12.0)
    pitch, yaw = math.radians(25), math.radians(30)   # nose down 25 deg, then turned left 30 deg
    q_pitch = np.array([math.cos(pitch / 2), 0, math.sin(pitch / 2), 0])
    q_yaw = np.array([math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)])
    quat = trimesh.transformations.quaternion_multiply(q_yaw, q_pitch)
    cp, sp, cy, sy = math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    rot = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    pose = np.array([[4.0, -2.0, 0.0, *quat]])
    depth = render(backend, scene_of(floor), [cam], pose)["d"][0, 0]
    expected = analytic_zdepth(cam, rot, -1.0, 0.0)
    assert (expected == cam.far).any() and (expected < cam.far).any()   # the horizon is in view
    # pixels whose floor point sits right at the far plane may fall either side of it
    clear = np.abs(expected - cam.far) > 0.05
    np.testing.assert_allclose(depth[clear], expected[clear], atol=DEPTH_TOL[backend])


@pytest.mark.parametrize("backend", BACKENDS)
def test_downward_mount_sees_floor_at_constant_depth(backend):
    floor = box((200, 200, 0.02), (0, 0, -1.51))
    down = (math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0)
    cam = CameraSpec("d", "depth", 16, 16, rotation=down)
    out = render(backend, scene_of(floor), [cam], IDENTITY)
    np.testing.assert_allclose(out["d"], 1.5, atol=DEPTH_TOL[backend])


@pytest.mark.parametrize("backend", BACKENDS)
def test_image_up_is_body_z_and_image_right_is_body_minus_y(backend):
    target = box((0.2, 0.4, 0.4), (3.0, 1.0, 1.0))    # ahead, to the left (+y), above (+z)
    cam = CameraSpec("s", "segmentation", 32, 32)
    seg = render(backend, scene_of(target, ids=[9]), [cam], IDENTITY)["s"][0, 0]
    rows, cols = np.nonzero(seg == 9)
    assert len(rows) > 0
    assert rows.max() < 16 and cols.max() < 16                   # top-left quadrant


@pytest.mark.parametrize("backend", BACKENDS)
def test_misses_give_far_nothing_and_sky(backend):
    behind = box((1, 1, 1), (-5, 0, 0))
    cams = [CameraSpec("d", "depth", 8, 6, far=15.0), CameraSpec("s", "segmentation", 8, 6),
            CameraSpec("c", "rgb", 8, 6)]
    out = render(backend, scene_of(behind), cams, IDENTITY)
    assert np.all(out["d"] == 15.0)
    assert out["s"].dtype == np.uint16 and np.all(out["s"] == 0)
    assert out["c"].shape == (1, 3, 6, 8) and out["c"].dtype == np.uint8
    np.testing.assert_array_equal(out["c"][0, :, 3, 4], SKY_RGB)


@pytest.mark.parametrize("backend", BACKENDS)
def test_beyond_far_and_nearer_than_near_are_not_seen(backend):
    far_wall = box((0.02, 40, 40), (30, 0, 0))
    tiny = box((0.01, 0.01, 0.01), (0.02, 0, 0))      # within the near plane (0.05 m)
    cam = CameraSpec("d", "depth", 8, 8, far=20.0)
    depth = render(backend, scene_of(far_wall, tiny), [cam], IDENTITY)["d"]
    assert np.all(depth == 20.0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_red_box_is_red(backend):
    red = box((1, 10, 10), (3, 0, 0), colour=(220, 20, 20))
    rgb = render(backend, scene_of(red), [CameraSpec("c", "rgb", 16, 16)], IDENTITY)["c"][0]
    r, g, b = (rgb[k].astype(float).mean() for k in range(3))
    assert r > 60 and g < 0.35 * r and b < 0.35 * r, (r, g, b)


@pytest.mark.parametrize("backend", BACKENDS)
def test_segmentation_ids_are_exact_including_high_ids(backend):
    left = box((0.2, 2, 2), (3, 1.2, 0))
    right = box((0.2, 2, 2), (3, -1.2, 0))
    cam = CameraSpec("s", "segmentation", 32, 16)
    seg = render(backend, scene_of(left, right, ids=[5, 40000]), [cam], IDENTITY)["s"][0, 0]
    assert set(np.unique(seg)) == {0, 5, 40000}
    assert np.all(seg[8, 5:13] == 5) and np.all(seg[8, 19:27] == 40000)


@pytest.mark.parametrize("backend", BACKENDS)
def test_other_drone_is_seen_and_own_drone_is_not(backend):
    empty = scene_of(box((1, 1, 1), (0, 0, -30)))
    cams = [CameraSpec("d", "depth", 21, 21, far=10.0), CameraSpec("s", "segmentation", 21, 21)]
    poses = np.array([[0.0, 0, 0, 1, 0, 0, 0], [2.0, 0, 0, 1, 0, 0, 0]])  # drone 1 two metres ahead of drone 0
    out = render(backend, empty, cams, poses, show_drones=True)
    assert out["d"][0, 0, 10, 10] == pytest.approx(2.0 - 0.1, abs=DEPTH_TOL[backend] + 5e-4)  # sphere of radius 0.1
    assert out["s"][0, 0, 10, 10] == drone_segmentation_id(1) == 65534
    assert np.all(out["d"][1] == 10.0) and np.all(out["s"][1] == 0)     # looks away; never sees itself
    hidden = render(backend, empty, cams, poses, show_drones=False)
    assert np.all(hidden["d"] == 10.0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_batch_of_poses_and_several_cameras(backend):
    wall = box((0.02, 40, 40), (5.01, 0, 0))
    cams = [CameraSpec("a", "depth", 12, 7), CameraSpec("b", "segmentation", 5, 9), CameraSpec("c", "rgb", 6, 4)]
    poses = np.tile(IDENTITY, (3, 1))
    poses[:, 0] = [0.0, 1.0, 2.0]
    out = render(backend, scene_of(wall), cams, poses)
    assert {k: v.shape for k, v in out.items()} == {"a": (3, 1, 7, 12), "b": (3, 1, 9, 5), "c": (3, 3, 4, 6)}
    np.testing.assert_allclose(out["a"][:, 0, 3, 6], [5.0, 4.0, 3.0], atol=DEPTH_TOL[backend])
    assert render(backend, scene_of(wall), cams, IDENTITY[:0])["a"].shape == (0, 1, 7, 12)


def test_bad_input_is_refused_with_the_reason():
    scene = scene_of(box((1, 1, 1), (3, 0, 0)))
    with make_renderer("raycast", scene, [CameraSpec()]) as r:
        with pytest.raises(ConfigError, match=r"poses shape \(3,\) must be \(n, 7\)"):
            r.render(np.zeros(3))
        with pytest.raises(ConfigError, match="NaN"):
            r.render(np.full((1, 7), np.nan))
    with pytest.raises(ConfigError, match="renderer was closed"):
        r.render(IDENTITY)
    with pytest.raises(ConfigError, match="backend='vulkan' must be one of"):
        make_renderer("vulkan", scene, [CameraSpec()])
    with pytest.raises(ConfigError, match="unique"):
        make_renderer("raycast", scene, [CameraSpec("x"), CameraSpec("x")])


def test_auto_backend_picks_raycast_for_depth_and_egl_for_rgb_on_a_gpu(monkeypatch):
    from types import SimpleNamespace

    from visfly_dist.scene_worker import render_base

    depth_only = [CameraSpec("d", "depth"), CameraSpec("s", "segmentation")]
    assert resolve_backend("auto", depth_only) == "raycast"
    assert resolve_backend("egl", depth_only) == "egl"
    gpu = SimpleNamespace(renderer="NVIDIA H200/PCIe/SSE2", is_gpu=True)
    cpu = SimpleNamespace(renderer="llvmpipe (LLVM 15.0.6, 256 bits)", is_gpu=False)
    for device, want in ((gpu, "egl"), (cpu, "raycast"), (None, "raycast")):
        monkeypatch.setattr(render_base, "egl_device", lambda d=device: d)
        name, reason = choose_backend("auto", [*depth_only, CameraSpec("c", "rgb")])
        assert name == want, reason
        assert resolve_backend("auto", [CameraSpec("d", "depth", 320, 320)]) == want
        assert resolve_backend("auto", depth_only) == "raycast"
    monkeypatch.setattr(render_base, "egl_device", lambda: gpu)
    assert choose_backend("auto", [CameraSpec("c", "rgb")]) == ("egl", "an RGB camera: rasterised on the GPU (NVIDIA H200/PCIe/SSE2)")
    monkeypatch.setattr(render_base, "egl_device", lambda: cpu)
    assert "GPU EGL unavailable (the EGL device is 'llvmpipe" in choose_backend("auto", [CameraSpec("c", "rgb")])[1]


@pytest.mark.parametrize("backend", BACKENDS)
def test_drone_whose_centre_is_outside_the_view_still_shows_its_edge(backend):
    empty = scene_of(box((1, 1, 1), (0, 0, -30)))
    cam = CameraSpec("s", "segmentation", 201, 201)          # 90 deg: the left edge plane is y = x
    poses = np.array([[0.0, 0, 0, 1, 0, 0, 0], [2.0, 2.08, 0, 1, 0, 0, 0]])
    seg = render(backend, empty, [cam], poses, show_drones=True)["s"][0, 0]
    assert (seg[:, 0] == 65534).any() and (seg[:, 3:] == 0).all()
