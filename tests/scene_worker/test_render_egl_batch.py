"""The batch egl renderer against the ray tracer (depth, ids, lit colours), and its own machinery:
several cameras per agent, 100 cameras in one call, moving obstacles, other drones, atlases split
into several passes, the unculled fallback, and the EGL device choice (headless, named errors)."""

from __future__ import annotations

import os
import resource
import subprocess
import sys

import numpy as np
import pytest
import trimesh
from scipy.ndimage import maximum_filter, minimum_filter

from tests.scene_worker.test_render_agreement import random_poses
from tests.scene_worker.test_shading import textured_quad
from visfly_dist.errors import ConfigError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.scene_worker import render_egl
from visfly_dist.scene_worker.render_base import available_backends, make_renderer, render_scenes_into
from visfly_dist.scenes import generate_scene
from visfly_dist.scenes.motion import Circle
from visfly_dist.scenes.scene import Scene, SceneObject

pytestmark = pytest.mark.skipif(set(available_backends()) != {"raycast", "egl"}, reason="needs both backends")

RIG = (CameraSpec("depth", "depth", 48, 36), CameraSpec("seg", "segmentation", 48, 36),
       CameraSpec("rgb", "rgb", 40, 30, offset=(0.05, 0.0, 0.02), rotation=(0.9659258, 0.0, 0.2588190, 0.0)))


def both(scene, cameras, poses, show_drones=False, time=0.0, **egl_options):
    out = {}
    for backend in ("raycast", "egl"):
        with make_renderer(backend, scene, cameras, drone_radius=0.1, **(egl_options if backend == "egl" else {})) as r:
            assert r.name == backend
            out[backend] = r.render(poses, show_drones=show_drones, time=time)
    return out["raycast"], out["egl"]


def non_edge(depth: np.ndarray, seg: np.ndarray) -> np.ndarray:
    size = (1, 3, 3)
    one_object = maximum_filter(seg, size) == minimum_filter(seg, size)
    smooth = maximum_filter(depth, size) - minimum_filter(depth, size) < 0.1 * depth
    return one_object & smooth


def assert_agree(ray: dict, egl: dict, depth="depth", seg="seg", rgb=None, rgb_levels=3.0, share=0.2):
    """Depth within today's egl tolerance and ids equal away from edges; RGB within a few levels there."""
    d_ray, d_egl = ray[depth][:, 0], egl[depth][:, 0]
    s_ray, s_egl = ray[seg][:, 0], egl[seg][:, 0]
    mask = non_edge(d_ray, s_ray) & non_edge(d_egl, s_egl)
    assert mask.mean() > share
    diff = np.abs(d_ray - d_egl)[mask]
    assert np.median(diff) < 1e-3 and np.percentile(diff, 99) < 5e-3
    assert (s_ray == s_egl)[mask].mean() > 0.98
    assert (s_ray == s_egl).mean() > 0.95
    if rgb is not None:
        assert ray[rgb].shape == egl[rgb].shape and egl[rgb].dtype == np.uint8
        away = (non_edge(ray[rgb].astype(float).sum(1), s_ray) if ray[rgb].shape[2:] == s_ray.shape[1:] else None)
        colours = np.abs(ray[rgb].astype(int) - egl[rgb].astype(int)).max(axis=1)
        if away is not None:
            colours = colours[mask & away]
        assert np.median(colours) <= 1 and np.percentile(colours, 90) <= rgb_levels


def assert_same(got: dict, want: dict) -> None:
    """The same images up to float32 interpolation (a pixel centre on an edge may round either way)."""
    for name in want:
        assert got[name].shape == want[name].shape and got[name].dtype == want[name].dtype
        close = np.abs(got[name].astype(float) - want[name]) <= (1e-4 if name == "depth" else 0)
        assert close.mean() > 0.999, (name, close.mean())


def test_garage_with_drones_and_three_cameras_per_agent_matches_the_tracer():
    scene = generate_scene("garage-stones", seed=0)
    cams = (CameraSpec("depth", "depth", 48, 36), CameraSpec("seg", "segmentation", 48, 36),
            CameraSpec("rgb", "rgb", 48, 36))
    poses = random_poses(scene, 24, np.random.default_rng(7))
    poses[1, :3] = poses[0, :3] + [0.8, 0.0, 0.0]     # a drone right in front of another one's view
    poses[1, 3:] = poses[0, 3:] = [1.0, 0.0, 0.0, 0.0]
    ray, egl = both(scene, cams, poses, show_drones=True)
    assert_agree(ray, egl, rgb="rgb")
    assert (egl["seg"][0, 0] == 65534).sum() > 20 and (egl["seg"][1, 0] == 65535).sum() == 0   # own drone unseen
    seen = egl["seg"][0, 0] == 65534
    assert np.abs(egl["rgb"][0][:, seen].astype(int) - ray["rgb"][0][:, seen]).mean() < 3   # drone shading


def test_mounted_cameras_of_other_sizes_match_the_tracer():
    scene = generate_scene("garage-stones", seed=1)
    cams = RIG + (CameraSpec("seg_rgb", "segmentation", 40, 30, offset=(0.05, 0.0, 0.02),
                             rotation=(0.9659258, 0.0, 0.2588190, 0.0)),)
    poses = random_poses(scene, 12, np.random.default_rng(3))
    ray, egl = both(scene, cams, poses)
    assert_agree(ray, egl)
    s_ray, s_egl = ray["seg_rgb"][:, 0], egl["seg_rgb"][:, 0]
    inner = (maximum_filter(s_ray, (1, 3, 3)) == minimum_filter(s_ray, (1, 3, 3)))
    assert (s_ray == s_egl)[inner].mean() > 0.98
    colours = np.abs(ray["rgb"].astype(int) - egl["rgb"].astype(int)).max(axis=1)[inner]
    assert np.median(colours) <= 1 and np.percentile(colours, 90) <= 3


def test_hundred_cameras_in_one_call_match_the_tracer_and_one_by_one():
    scene = generate_scene("garage-stones", seed=0)
    cams = (CameraSpec("depth", "depth", 32, 32), CameraSpec("seg", "segmentation", 32, 32))
    poses = random_poses(scene, 50, np.random.default_rng(11))    # 50 agents x 2 cameras
    ray, egl = both(scene, cams, poses, show_drones=True)
    assert_agree(ray, egl, share=0.15)     # small images: fewer pixels away from edges
    with make_renderer("egl", scene, cams) as r:
        single = [r.render(poses[k:k + 1], show_drones=False) for k in (0, 17, 49)]
        batch = r.render(poses, show_drones=False)
    for k, one in zip((0, 17, 49), single):     # same images wherever the tile lies in the atlas
        assert_same(one, {name: image[k:k + 1] for name, image in batch.items()})


def test_atlas_split_in_columns_and_passes_lanes_and_the_unculled_path_give_the_same_images(monkeypatch):
    scene = generate_scene("garage-stones", seed=0)
    poses = random_poses(scene, 30, np.random.default_rng(5))
    cams = RIG
    with make_renderer("egl", scene, cams) as r:
        want = r.render(poses, show_drones=True)
    monkeypatch.setattr("visfly_dist.scene_worker.render_egl_batch.MAX_ATLAS", 150)   # 4 tiles a column, 3 a pass
    with make_renderer("egl", scene, cams) as r:
        got = r.render(poses, show_drones=True)
        assert r._max_side == 150
    monkeypatch.undo()
    for lanes in (1, 3):    # drones split between contexts drawing at once, each seeing every drone
        with make_renderer("egl", scene, cams, lanes=lanes) as r:
            assert_same(r.render(poses, show_drones=True), want)
            assert len(r._lanes) == lanes - 1
    monkeypatch.setenv("VISFLY_EGL_CULL", "0")
    with make_renderer("egl", scene, cams) as r:
        unculled = r.render(poses, show_drones=True)
        assert not r._indirect
    assert_same(got, want)
    assert_same(unculled, want)


def _moving_scene() -> Scene:
    floor = trimesh.creation.box(extents=(20, 20, 0.1), transform=trimesh.transformations.translation_matrix([5, 0, -0.05]))
    objects = [SceneObject("floor", 1, floor)]
    for k in range(3):
        cube = trimesh.creation.box(extents=(0.6, 0.6, 0.6))
        cube.visual.face_colors = [200, 60 * k, 30, 255]
        objects.append(SceneObject(f"cube{k}", 2 + k, cube, Circle([4.0, 0.0, 1.0 + 0.5 * k], 1.5, 1.1, phase=2.0 * k)))
    return Scene("moving", objects, np.array([[-2, -6, 0], [10, 6, 4]]))


def test_moving_obstacles_match_the_tracer_at_each_time():
    scene = _moving_scene()
    cams = (CameraSpec("depth", "depth", 48, 36), CameraSpec("seg", "segmentation", 48, 36), CameraSpec("rgb", "rgb", 48, 36))
    poses = np.array([[0.0, y, 1.2, 1.0, 0.0, 0.0, 0.0] for y in (-1.0, 0.0, 1.0)])
    with make_renderer("raycast", scene, cams) as ray_r, make_renderer("egl", scene, cams) as egl_r:
        for t in (0.0, 1.7, 5.2):
            ray, egl = ray_r.render(poses, time=t), egl_r.render(poses, time=t)
            assert_agree(ray, egl, rgb="rgb")
            assert np.isin(egl["seg"], [2, 3, 4]).any()


def test_a_textured_wall_matches_the_tracer_texel_for_texel():
    mesh = textured_quad()
    scene = Scene("tex", [SceneObject("wall", 1, mesh)], np.array([[-5.0, -5.0, -5.0], [5.0, 5.0, 5.0]]))
    cams = (CameraSpec("rgb", "rgb", 64, 64), CameraSpec("seg", "segmentation", 64, 64), CameraSpec("depth", "depth", 64, 64))
    ray, egl = both(scene, cams, np.array([[0.0, 0.3, 0.2, 1.0, 0.0, 0.0, 0.0]]))
    wall = minimum_filter(ray["seg"][0, 0], 3) > 0
    diff = np.abs(ray["rgb"][0].astype(int) - egl["rgb"][0])[:, wall]
    assert wall.sum() > 1000 and diff.max() <= 2 and diff.mean() < 0.6
    assert len(np.unique(egl["rgb"][0][:, wall].T, axis=0)) > 8
    np.testing.assert_array_equal(egl["rgb"][0][:, ~(maximum_filter(ray["seg"][0, 0], 3) > 0)].T[0], [150, 180, 210])


def test_camera_inside_a_closed_solid_sees_its_inside_like_the_tracer():
    stone = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    stone.visual.face_colors = [90, 120, 60, 255]
    scene = Scene("inside", [SceneObject("stone", 7, stone)], np.array([[-5.0, -5.0, -5.0], [5.0, 5.0, 5.0]]))
    cams = (CameraSpec("depth", "depth", 32, 24), CameraSpec("seg", "segmentation", 32, 24))
    poses = np.array([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], [-1.02, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])  # inside; at the skin
    ray, egl = both(scene, cams, poses)
    assert (egl["seg"][0] == 7).all()
    assert_agree(ray, egl)


def test_render_scenes_into_writes_the_given_rows():
    scene = generate_scene("garage-stones", seed=0)
    cams = (CameraSpec("depth", "depth", 24, 16), CameraSpec("rgb", "rgb", 24, 16))
    poses = random_poses(scene, 6, np.random.default_rng(2))
    out = {c.name: np.zeros((10, *c.shape), c.dtype) for c in cams}
    with make_renderer("egl", scene, cams) as r:
        want = r.render(poses)
        r.render = None    # the images are read back straight into out, never rendered apart and copied
        render_scenes_into([(r, poses[:2], False), (r, poses[2:], False)], out, starts=[0, 6])
    assert_same({k: v[:2] for k, v in out.items()}, {k: v[:2] for k, v in want.items()})
    assert_same({k: v[6:] for k, v in out.items()}, {k: v[2:] for k, v in want.items()})
    assert not out["depth"][2:6].any() and not out["rgb"][2:6].any()


def test_device_index_follows_egl_device_id_then_cuda_visible_devices(monkeypatch):
    monkeypatch.delenv("EGL_DEVICE_ID", raising=False)
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    assert render_egl.egl_device_index() == (0, "default")
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "3,1")
    assert render_egl.egl_device_index() == (3, "CUDA_VISIBLE_DEVICES")
    monkeypatch.setenv("EGL_DEVICE_ID", "1")
    assert render_egl.egl_device_index() == (1, "EGL_DEVICE_ID")
    monkeypatch.setenv("EGL_DEVICE_ID", "gpu")
    with pytest.raises(ConfigError, match="EGL_DEVICE_ID='gpu' must be a device index"):
        render_egl.egl_device_index()


def test_a_missing_device_is_one_clear_error_and_the_path_is_headless():
    code = ("import sys\n"
            "from visfly_dist.scene_worker.render_egl_batch import BatchEglRenderer\n"
            "from visfly_dist.scene_worker.render_egl import gl_device\n"
            "assert not {'pyrender', 'pyglet'} & set(sys.modules), sorted(m for m in sys.modules if 'py' in m)\n"
            "try:\n    gl_device()\nexcept Exception as e:\n    print(type(e).__name__, e)\n")
    env = {**os.environ, "EGL_DEVICE_ID": "99", "DISPLAY": ""}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("ConfigError the egl backend has no usable EGL device: EGL device 99 (from EGL_DEVICE_ID)")
    assert "--backend raycast" in out.stdout


def test_the_device_is_named():
    device = render_egl.gl_device()
    assert device.renderer and device.version
    assert device.is_gpu == ("llvmpipe" not in device.renderer.lower())


def test_on_a_cpu_rasteriser_lanes_follow_the_cores_and_frames_reuse_the_heap():
    from visfly_dist.host import usable_cores
    from visfly_dist.scene_worker.render_egl_batch import MAX_DEFAULT_LANES

    device = render_egl.gl_device()
    scene = generate_scene("garage-stones", seed=0)
    poses = random_poses(scene, 40, np.random.default_rng(4))
    with make_renderer("egl", scene, (CameraSpec("depth", "depth", 64, 64),)) as r:
        assert r.lanes == (1 if device.is_gpu else min(MAX_DEFAULT_LANES, usable_cores()))
        r.render(poses)
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for _ in range(3):
            r.render(poses)
        faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 3
    if not device.is_gpu:   # llvmpipe's binned triangles (~6 MB a frame here) come from kept heap: ~80, not ~4,500
        assert faults < 1000


def test_renderers_share_the_process_lanes_and_one_closing_leaves_the_others_drawing():
    scene = generate_scene("garage-stones", seed=0)
    poses = random_poses(scene, 24, np.random.default_rng(6))
    cams = (CameraSpec("depth", "depth", 32, 24),)
    with make_renderer("egl", scene, cams, lanes=2) as first, make_renderer("egl", scene, cams, lanes=2) as second:
        want = first.render(poses)
        second.render(poses)
        assert len(first._lanes) == 1 and first._lanes == second._lanes   # one extra context for both
        first.close()
        assert_same(second.render(poses), want)


@pytest.mark.worker
def test_an_egl_worker_names_its_gl_device_in_the_ready_line_and_health(scene_root):
    from tests.helpers import REPO, _read_line, call, client_session, free_port, stop_process, worker_argv
    from visfly_dist.protocol import keys
    from visfly_dist.protocol.messages import Health

    device = render_egl.gl_device().renderer
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(worker_argv("egl-device", endpoint, scene_root, backend="egl", worker_id="we"),
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env, cwd=REPO)
    try:
        line = _read_line(proc, 60.0)
        assert "worker we ready on run egl-device: backend egl, tracer " in line, line
        assert f", GL device {device!r}, listening on" in line, line
        with client_session(endpoint) as session:
            ok, reply = call(session, keys.worker_rpc("egl-device", "we"), Health().to_message())
        assert ok and reply["backend"] == "egl" and reply["gl_device"] == device
    finally:
        stop_process(proc)


def test_chunks_cover_every_face_once_and_keep_small_objects_whole():
    from visfly_dist.scene_worker.render_egl_batch import CHUNK_FACES, _Geometry

    scene = generate_scene("garage-stones", seed=0)
    geometry = _Geometry(scene, rgb=True)
    starts, ends = geometry.chunks[:, 0].astype(int), geometry.chunks[:, 1].astype(int)
    assert starts[0] == 0 and (starts[1:] == ends[:-1]).all() and ends[-1] == scene.num_triangles
    assert ((ends - starts) <= CHUNK_FACES).all() and (ends > starts).all()
    assert sorted(geometry.order.tolist()) == list(range(scene.num_triangles))
    assert len(geometry.corners) == 3 * scene.num_triangles
    vertices = geometry.indexed[:, :3][geometry.indices.reshape(-1, 3)]        # the chunk spheres hold their faces
    for start, end, *centre_radius in geometry.chunks[:, :6]:
        centre, radius = np.array(centre_radius[:3]), centre_radius[3]
        assert (np.linalg.norm(vertices[int(start):int(end)] - centre, axis=2) <= radius + 1e-4).all()
