"""The native packet tracer against the embreex path (bit for bit) and analytic planes; its fallback."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from tests.helpers import REPO, _read_line, call, client_session, free_port, stop_process, worker_argv
from tests.scene_worker.test_render import analytic_zdepth, box, scene_of
from visfly_dist.errors import ConfigError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.session import SessionConfig
from visfly_dist.scene_worker import render_native
from visfly_dist.scene_worker.camera_math import quat_to_matrix
from visfly_dist.scene_worker.render_base import choose_backend, render_scenes
from visfly_dist.scene_worker.render_raycast import RaycastRenderer
from visfly_dist.scenes import generate_scene

needs_native = pytest.mark.skipif(not render_native.available(),
                                  reason=f"native tracer unavailable: {render_native.load_library()[1]}")


@pytest.fixture(scope="module")
def garage():
    return generate_scene("garage-stones", seed=0)


def garage_poses(scene, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    low, high = scene.bounds
    pos = rng.uniform(low + [1.0, 1.0, 0.5], high - [1.0, 1.0, 0.5], size=(n, 3))
    quat = rng.normal(size=(n, 4)) * [1.0, 0.15, 0.15, 1.0]
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    poses = np.concatenate([pos, quat], axis=1)
    poses[1, :3] = poses[0, :3] + quat_to_matrix(poses[0, 3:]) @ [0.8, 0.0, 0.0]  # drone 1 in drone 0's view
    return poses


def cameras(res: int) -> list[CameraSpec]:
    """Several cameras per drone: all three kinds, one mounted off-centre and pitched, one not a multiple of 4."""
    pitch = [np.cos(0.2), 0.0, np.sin(0.2), 0.0]
    return [CameraSpec("d", "depth", res, res), CameraSpec("s", "segmentation", res, res),
            CameraSpec("c", "rgb", res, res),
            CameraSpec("m", "depth", res + 3, res // 2 + 1, hfov_deg=70, offset=(0.1, 0.05, -0.02), rotation=pitch)]


@needs_native
@pytest.mark.parametrize("res, agents", [(64, 12), (128, 6), (256, 3)])
def test_native_matches_embreex_bit_for_bit_with_drones(garage, res, agents):
    poses = garage_poses(garage, agents, seed=res)
    out = {}
    for tracer in ("native", "embreex"):
        with RaycastRenderer(garage, cameras(res), drone_radius=0.1, threads=2, tracer=tracer) as r:
            assert r.tracer == tracer
            out[tracer] = r.render(poses, show_drones=True)
    for name, native in out["native"].items():
        np.testing.assert_array_equal(native, out["embreex"][name], err_msg=f"camera {name} at {res} px")
    assert (out["native"]["s"][0] == 65534).sum() > 10                 # drone 1 seen by drone 0
    assert len(np.unique(out["native"]["s"])) > 3                      # several scene objects too
    assert (out["native"]["d"] < 20.0).mean() > 0.9


@needs_native
def test_native_draws_a_swarm_like_embreex(garage):
    """30 drones within 1.5 m of each other: spheres overlapping in view, one the camera is inside of,
    one cut by the near plane; every pixel of every kind equal to the embreex path's."""
    rng = np.random.default_rng(11)
    centre = garage_poses(garage, 2, seed=1)[0, :3]
    poses = np.concatenate([centre + rng.uniform(-1.5, 1.5, (30, 3)), rng.normal(size=(30, 4))], axis=1)
    poses[:, 3:] /= np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)
    poses[1, :3] = poses[0, :3] + [0.05, 0.0, 0.0]                     # drone 0's camera inside drone 1
    cams = [CameraSpec("d", "depth", 48, 40, near=0.12), CameraSpec("s", "segmentation", 33, 30),
            CameraSpec("c", "rgb", 40, 32)]
    out = {}
    for tracer in ("native", "embreex"):
        with RaycastRenderer(garage, cams, drone_radius=0.15, threads=2, tracer=tracer) as r:
            out[tracer] = r.render(poses, show_drones=True)
    for name in ("d", "s", "c"):
        np.testing.assert_array_equal(out["native"][name], out["embreex"][name], err_msg=name)
    seg = out["native"]["s"]
    assert (seg >= 65535 - 29).sum() > 500 and len(np.unique(seg[seg >= 65535 - 29])) > 10
    assert (seg[0] == 65534).all()                                       # inside drone 1: its far side


@needs_native
def test_native_hit_data_for_shading_matches_embreex(garage):
    cam = CameraSpec("c", "rgb", 40, 28)
    poses = garage_poses(garage, 4, seed=5)
    with RaycastRenderer(garage, [cam], tracer="native") as native, \
            RaycastRenderer(garage, [cam], tracer="embreex") as embreex:
        plan = native._plan(poses, show_drones=False)
        render_native.trace(plan.batches, threads=2)
        expected = embreex._trace_embreex(cam, poses)
    (batch,) = plan.batches
    np.testing.assert_array_equal(batch.prim.reshape(4, -1), expected.prim)
    assert (expected.prim >= 0).mean() > 0.9
    np.testing.assert_allclose(batch.uv.reshape(4, -1, 2), expected.uv, atol=1e-5)
    assert ((batch.uv >= 0) & (batch.uv <= 1)).all()


@needs_native
@pytest.mark.parametrize("res", [64, 128, 256])
def test_native_depth_of_a_tilted_floor_is_analytic(res):
    floor = box((60, 60, 0.02), (0, 0, -0.01))
    cam = CameraSpec("d", "depth", res, res // 2 + 3, hfov_deg=100)
    height, pitch = 1.5, 0.5                                   # looking 0.5 rad down at a floor 1.5 m below
    quat = np.array([np.cos(pitch / 2), 0.0, np.sin(pitch / 2), 0.0])
    poses = np.array([[0.0, 0.0, height, *quat]])
    with RaycastRenderer(scene_of(floor), [cam], tracer="native") as r:
        depth = r.render(poses)["d"][0, 0]
    expected = analytic_zdepth(cam, quat_to_matrix(quat), 0.0, height)
    assert (expected < cam.far).mean() > 0.5
    np.testing.assert_allclose(depth, expected, rtol=1e-5, atol=1e-5)


@needs_native
def test_near_and_far_clip_like_embreex():
    wall = box((0.02, 40, 40), (3.01, 0, 0))
    cams = [CameraSpec("close", "depth", 16, 16, far=2.0), CameraSpec("past", "depth", 16, 16, near=3.5)]
    r = RaycastRenderer(scene_of(wall), cams, tracer="native")
    out = r.render(np.array([[0.0, 0, 0, 1, 0, 0, 0]]))
    r.close()
    assert (out["close"] == 2.0).all() and (out["past"] == 20.0).all()


@needs_native
def test_render_scenes_traces_64_scenes_in_one_native_call(garage, monkeypatch):
    rng = np.random.default_rng(3)
    cam = [CameraSpec("d", "depth", 32, 32), CameraSpec("s", "segmentation", 24, 16)]
    scenes = [scene_of(box((1, 1, 1), (3.0, y, 0.0)), box((40, 40, 0.1), (0, 0, -1.0)), ids=[1 + k % 7, 9])
              for k, y in enumerate(rng.uniform(-1.0, 1.0, 64))]
    renderers = [RaycastRenderer(s, cam, threads=2, tracer="native") for s in scenes]
    poses = [np.array([[0.0, 0.0, rng.uniform(-0.3, 0.3), 1, 0, 0, 0]]) for _ in scenes]
    separate = [r.render(p) for r, p in zip(renderers, poses)]
    # one embreex scene and one multi-agent scene in the same call
    fallback = RaycastRenderer(scenes[0], cam, tracer="embreex")
    pair = np.array([[0.0, 0, 0, 1, 0, 0, 0], [1.0, 0.1, 0, 1, 0, 0, 0]])
    items = [(r, p, False) for r, p in zip(renderers, poses)] + [(fallback, poses[0], False), (renderers[1], pair, True)]
    calls = []
    original = render_native.trace
    monkeypatch.setattr(render_native, "trace", lambda batches, threads: calls.append(len(batches)) or
                        original(batches, threads))
    together = render_scenes(items)
    assert calls == [2 * 65]                               # every camera of every native scene, once
    for one, other in zip(separate + [separate[0]], together):
        for name in one:
            np.testing.assert_array_equal(one[name], other[name])
    np.testing.assert_array_equal(together[-1]["s"], renderers[1].render(pair, show_drones=True)["s"])
    assert (together[-1]["s"][0] == 65534).any()
    for r in [*renderers, fallback]:
        r.close()


def test_render_scenes_validates_every_item_before_rendering():
    r = RaycastRenderer(scene_of(box((1, 1, 1), (3, 0, 0))), [CameraSpec()], tracer="embreex")
    with pytest.raises(ConfigError, match=r"poses shape \(7,\) must be \(n, 7\)"):
        render_scenes([(r, np.zeros((1, 7)) + [0, 0, 0, 1, 0, 0, 0], False), (r, np.zeros(7), False)])
    r.close()
    with pytest.raises(ConfigError, match="renderer was closed"):
        render_scenes([(r, np.array([[0.0, 0, 0, 1, 0, 0, 0]]), False)])


@pytest.fixture
def no_native(monkeypatch, tmp_path):
    """The native library forced missing (a path where nothing is built)."""
    monkeypatch.delenv(render_native.DISABLE_ENV, raising=False)
    monkeypatch.setattr(render_native, "LIBRARY_PATH", tmp_path / "libvisfly_tracer.so")
    render_native.load_library.cache_clear()
    yield tmp_path / "libvisfly_tracer.so"
    render_native.load_library.cache_clear()


def test_fallback_to_embreex_when_the_library_is_missing(no_native):
    lib, reason = render_native.load_library()
    assert lib is None and "not built" in reason and str(no_native) in reason
    wall = box((0.02, 40, 40), (3.01, 0, 0))
    with RaycastRenderer(scene_of(wall), [CameraSpec("d", "depth", 8, 8)]) as r:
        assert r.tracer == "embreex"
        np.testing.assert_allclose(r.render(np.array([[0.0, 0, 0, 1, 0, 0, 0]]))["d"], 3.0, atol=1e-5)
        assert render_scenes([(r, np.array([[0.0, 0, 0, 1, 0, 0, 0]]), False)])[0]["d"].shape == (1, 1, 8, 8)
    with pytest.raises(ConfigError, match="tracer 'native' is unavailable: .* not built"):
        RaycastRenderer(scene_of(wall), [CameraSpec()], tracer="native")
    assert choose_backend("auto", [CameraSpec("d", "depth", 256, 256)])[0] in ("egl", "raycast")
    from visfly_dist.scene_worker.service import SceneWorker

    health = SceneWorker("r", SessionConfig(listen=("tcp/127.0.0.1:1",)), [str(no_native.parent)]).health()
    assert health["tracer"] == "embreex"


def test_a_library_that_fails_to_load_falls_back(no_native):
    no_native.write_bytes(b"not a shared object")
    lib, reason = render_native.load_library()
    assert lib is None and "failed to load" in reason
    with RaycastRenderer(scene_of(box((1, 1, 1), (3, 0, 0))), [CameraSpec()]) as r:
        assert r.tracer == "embreex"


def test_bad_tracer_and_threads_are_named():
    scene = scene_of(box((1, 1, 1), (3, 0, 0)))
    with pytest.raises(ConfigError, match=r"tracer='optix' must be one of \('native', 'embreex'\)"):
        RaycastRenderer(scene, [CameraSpec()], tracer="optix")
    with pytest.raises(ConfigError, match="threads=0 must be an int >= 1"):
        RaycastRenderer(scene, [CameraSpec()], threads=0)


@needs_native
def test_auto_keeps_raycast_up_to_256_pixels_with_the_native_tracer():
    assert choose_backend("auto", [CameraSpec("d", "depth", 256, 256)])[0] == "raycast"
    name, reason = choose_backend("auto", [CameraSpec("d", "depth", 257, 256)])
    assert name == "egl" or "EGL unavailable" in reason


@needs_native
@pytest.mark.worker
def test_worker_states_its_tracer_in_health_and_log(worker_factory):
    from visfly_dist.protocol.messages import Health

    proc = worker_factory("native-health", extra_args=["--threads", "2"])
    with client_session(proc.endpoint) as session:
        ok, reply = call(session, proc.rpc_key, Health().to_message())
    assert ok and reply["tracer"] == "native"
    assert "raycast tracer native" in proc.stderr_text()


@pytest.mark.worker
def test_worker_ready_line_names_the_fallback_tracer(scene_root):
    env = {**os.environ, "PYTHONPATH": str(REPO), "VISFLY_NATIVE_TRACER": "0"}
    proc = subprocess.Popen(worker_argv("fallback-line", f"tcp/127.0.0.1:{free_port()}", scene_root, worker_id="wf"),
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env, cwd=REPO)
    try:
        line = _read_line(proc, 60.0)
    finally:
        stop_process(proc)
    assert "worker wf ready on run fallback-line: backend raycast, tracer embreex, listening on" in line


def test_worker_rejects_zero_threads():
    out = subprocess.run([sys.executable, "-m", "visfly_dist.cli", "worker", "--run-id", "t", "--listen",
                          "tcp/127.0.0.1:0", "--threads", "0"], capture_output=True, text=True, timeout=60,
                         env={**os.environ, "PYTHONPATH": str(REPO)}, cwd=REPO)
    assert out.returncode == 2 and "--threads 0 must be >= 1" in out.stderr and "ready" not in out.stdout
