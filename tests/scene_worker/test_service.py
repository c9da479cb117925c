"""A real worker process serving the protocol, over shared memory and over plain TCP.

Every answer is cross-checked against the same renderer and queries run in this process.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import struct

import msgpack
import numpy as np
import pytest

from tests.helpers import call, client_session
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.codec import MAGIC, PROTOCOL_VERSION, encode
from visfly_dist.protocol.messages import (
    Health, LoadScene, SampleSpawn, ScenePoses, StepRequest, UnloadScene, split_step_result,
)
from visfly_dist.protocol import shm
from visfly_dist.scene_worker.queries import ObstacleQueries
from visfly_dist.scene_worker.render_base import make_renderer
from visfly_dist.scenes import resolve_source

pytestmark = pytest.mark.worker

RUN = f"svc{os.getpid()}"
SOURCE = "gen:pillars?seed=1"
CAMERAS = (CameraSpec(name="depth", width=64, height=48), CameraSpec(name="seg", kind="segmentation", width=32, height=32))
RADIUS = 0.1


@pytest.fixture(scope="module", params=["shm", "tcp"])
def worker(request, worker_factory):
    shm = request.param == "shm"
    proc = worker_factory(RUN, shm=shm)
    with client_session(proc.endpoint, shm=shm) as session:
        ok, reply = call(session, proc.rpc_key, LoadScene("s0", SOURCE, CAMERAS, drone_radius=RADIUS).to_message())
        assert ok, reply
        yield proc, session, reply


@pytest.fixture(scope="module")
def reference():
    """The scene, renderer and queries of the worker's scene, built in this process."""
    scene = resolve_source(SOURCE, [os.getcwd()])
    renderer = make_renderer("raycast", scene, CAMERAS, drone_radius=RADIUS)
    yield scene, renderer, ObstacleQueries(scene, drone_radius=RADIUS)
    renderer.close()


def _poses(scene, n: int, seed: int = 0) -> np.ndarray:
    """``n`` float32 poses inside the scene's bounds with random yaw (some near or inside obstacles)."""
    rng = np.random.default_rng(seed)
    low, high = scene.bounds
    pos = rng.uniform(low + 0.2, high - 0.2, size=(n, 3))
    yaw = rng.uniform(-np.pi, np.pi, n)
    quat = np.stack([np.cos(yaw / 2), np.zeros(n), np.zeros(n), np.sin(yaw / 2)], axis=1)
    return np.concatenate([pos, quat], axis=1).astype(np.float32)


def _step(proc, session, poses, key="s0", **kw):
    return call(session, proc.rpc_key, StepRequest((ScenePoses(key, poses),), **kw).to_message())


def test_load_reply_describes_the_scene(worker, reference):
    _, _, reply = worker
    scene = reference[0]
    assert reply["type"] == "scene_loaded" and reply["scene_key"] == "s0" and reply["backend"] == "raycast"
    assert reply["bounds"].dtype == np.float64
    np.testing.assert_array_equal(reply["bounds"], scene.bounds)
    assert reply["num_triangles"] == scene.num_triangles and reply["num_objects"] == len(scene.objects)
    assert reply["metadata"]["kind"] == scene.metadata["kind"]


def test_step_matches_in_process_render_and_queries(worker, reference):
    proc, session, _ = worker
    scene, renderer, queries = reference
    poses = _poses(scene, 20)
    ok, reply = _step(proc, session, poses, search_radius=3.0)
    assert ok, reply
    assert reply["counts"].tolist() == [20]
    (result,) = split_step_result(reply)
    depth, seg = result["images"]["depth"], result["images"]["seg"]
    assert depth.shape == (20, 1, 48, 64) and depth.dtype == np.float32
    assert seg.shape == (20, 1, 32, 32) and seg.dtype == np.uint16
    expected = renderer.render(poses.astype(np.float64))  # the wire carries float32 poses
    np.testing.assert_array_equal(depth, expected["depth"])
    np.testing.assert_array_equal(seg, expected["seg"])
    assert 0 < depth.min() and depth.max() <= CAMERAS[0].far and (depth < CAMERAS[0].far).any()

    q = queries.query(poses[:, :3].astype(np.float64), 3.0)
    assert result["collision"].dtype == bool and result["inside"].dtype == bool
    assert result["nearest"].dtype == np.float32 and result["nearest"].shape == (20, 3)
    assert result["distance"].dtype == np.float32 and result["distance"].shape == (20,)
    np.testing.assert_array_equal(result["collision"], q.collision)
    np.testing.assert_array_equal(result["inside"], q.inside)
    np.testing.assert_array_equal(result["nearest"], np.asarray(q.nearest, np.float32))
    np.testing.assert_array_equal(result["distance"], np.asarray(q.distance, np.float32))
    assert result["distance"].max() <= 3.0


def test_step_reports_its_timings_and_health_accumulates_them(worker):
    proc, session, _ = worker
    ok, reply = _step(proc, session, _poses_at_origin(3))
    assert ok, reply
    assert set(reply["timings"]) == {"decode_s", "render_s", "query_s", "encode_s", "total_s"}
    assert all(v >= 0 for v in reply["timings"].values())
    assert reply["timings"]["total_s"] >= reply["timings"]["render_s"] + reply["timings"]["query_s"]

    ok, health = call(session, proc.rpc_key, Health().to_message())
    assert ok, health
    assert health["type"] == "health" and health["worker_id"] == proc.worker_id and health["pid"] == proc.pid
    assert health["backend"] == "raycast" and "s0" in health["scenes"] and health["uptime_s"] > 0
    timings = health["timings"]
    for stage in ("decode", "render", "query", "encode", "reply", "step", "load_scene"):
        assert timings[stage]["count"] >= 1 and timings[stage]["total_s"] >= 0, stage


def _poses_at_origin(n: int) -> np.ndarray:
    poses = np.zeros((n, 7), np.float32)
    poses[:, 2] = 1.0
    poses[:, 3] = 1.0
    return poses


def test_render_and_query_can_be_skipped(worker):
    proc, session, _ = worker
    ok, reply = _step(proc, session, _poses_at_origin(2), render=False)
    assert ok and split_step_result(reply)[0]["images"] == {} and reply["distance"].shape == (2,)
    ok, reply = _step(proc, session, _poses_at_origin(2), query=False)
    assert ok and set(reply) == {"version", "type", "counts", "images", "timings"}
    assert split_step_result(reply)[0]["images"]["depth"].shape == (2, 1, 48, 64)


def test_step_of_zero_agents_gives_empty_arrays(worker):
    proc, session, _ = worker
    ok, reply = _step(proc, session, np.zeros((0, 7), np.float32))
    assert ok, reply
    result = split_step_result(reply)[0]
    assert result["images"]["depth"].shape == (0, 1, 48, 64) and result["nearest"].shape == (0, 3)


def test_sample_spawn_keeps_clearance_and_is_seeded(worker, reference):
    proc, session, _ = worker
    scene, _, queries = reference
    low, high = scene.bounds
    msg = SampleSpawn("s0", 30, 0.5, "uniform", tuple(low), tuple(high), seed=3).to_message()
    ok, reply = call(session, proc.rpc_key, msg)
    assert ok, reply
    pos = reply["positions"]
    assert reply["type"] == "spawn" and pos.shape == (30, 3) and pos.dtype == np.float32
    assert np.all(queries.distance(pos.astype(np.float64)) >= 0.5 - 1e-4)
    assert np.all(pos >= low + 0.5 - 1e-4) and np.all(pos <= high - 0.5 + 1e-4)
    ok, again = call(session, proc.rpc_key, msg)
    np.testing.assert_array_equal(again["positions"], pos)
    ok, other = call(session, proc.rpc_key, {**msg, "seed": 4})
    assert not np.array_equal(other["positions"], pos)


def test_several_scenes_in_one_step_and_reload_and_unload(worker):
    proc, session, _ = worker
    ok, reply = call(session, proc.rpc_key, LoadScene("s1", "gen:empty", CAMERAS).to_message())
    assert ok, reply
    poses = _poses_at_origin(4)
    step = StepRequest((ScenePoses("s0", poses[:3]), ScenePoses("s1", poses[3:]), ScenePoses("s0", poses[:2])))
    ok, reply = call(session, proc.rpc_key, step.to_message())
    assert ok, reply
    assert reply["counts"].tolist() == [3, 1, 2] and reply["images"]["depth"].shape[0] == 6
    first, empty, again = split_step_result(reply)
    np.testing.assert_array_equal(first["images"]["depth"][:2], again["images"]["depth"])
    assert empty["images"]["depth"].shape == (1, 1, 48, 64)

    ok, reply = call(session, proc.rpc_key, LoadScene("s2", "gen:empty", CAMERAS[:1]).to_message())
    ok, err = call(session, proc.rpc_key, StepRequest((ScenePoses("s0", poses), ScenePoses("s2", poses))).to_message())
    assert not ok and err["error"] == "ProtocolError" and "same cameras" in err["message"]
    assert call(session, proc.rpc_key, UnloadScene("s2").to_message())[0]

    ok, reply = call(session, proc.rpc_key, LoadScene("s1", "gen:pillars?seed=2", CAMERAS).to_message())
    assert ok and set(_step(proc, session, poses, key="s1")[1]["images"]) == {"depth", "seg"}

    assert call(session, proc.rpc_key, UnloadScene("s1").to_message()) == (True, {"version": PROTOCOL_VERSION, "type": "ok"})
    ok, err = _step(proc, session, poses, key="s1")
    assert not ok and err["error"] == "SceneError" and err["code"] == "unknown_scene"
    assert "'s1' is not loaded" in err["message"]
    ok, health = call(session, proc.rpc_key, Health().to_message())
    assert health["scenes"] == ["s0"]


def _good_step() -> dict:
    return StepRequest((ScenePoses("s0", _poses_at_origin(2)),)).to_message()


def _with_poses(poses) -> dict:
    return {**_good_step(), "keys": ["s0"], "counts": np.array([len(poses)], np.int32), "poses": poses}


def _nan_poses() -> np.ndarray:
    poses = _poses_at_origin(2)
    poses[1, 1] = np.nan
    return poses


def _framed(header: bytes) -> bytes:
    return struct.pack("<4sI", MAGIC, len(header)) + header


MALFORMED = {
    "random bytes": (bytes(range(7, 200, 3)), "ProtocolError", "does not start with the framing"),
    "empty payload": (b"", "ProtocolError", "does not start with the framing"),
    "garbage header": (_framed(b"\xc1\xff"), "ProtocolError", "not a valid msgpack message"),
    "not a map": (_framed(msgpack.packb([1, 2])), "ProtocolError", "must be a map"),
    "wrong version": (_framed(msgpack.packb({"version": 999, "type": "health"})), "ProtocolError", "protocol version 999"),
    "unknown type": ({"type": "explode"}, "ProtocolError", "valid types: load_scene, unload_scene, step, sample_spawn, health"),
    "poses wrong shape": (_with_poses(np.zeros((2, 6), np.float32)), "ProtocolError", "must be \\(n, 7\\)"),
    "poses wrong dtype": (_with_poses(np.zeros((2, 7), np.uint8)), "ProtocolError", "dtype uint8 must be float32"),
    "poses NaN": (_with_poses(_nan_poses()), "ProtocolError", "NaN or infinite"),
    "absurd batch": (_with_poses(np.tile(_poses_at_origin(1), (100_001, 1))), "ProtocolError", "exceed the bound 100000"),
    "path escape": (LoadScene("evil", "../../etc/passwd", CAMERAS).to_message(), "SceneError", "outside the scene roots"),
    "missing file": (LoadScene("gone", "no/such/scene.glb", CAMERAS).to_message(), "SceneError", "no/such/scene.glb"),
    "unknown generator": (LoadScene("g", "gen:volcano", CAMERAS).to_message(), "SceneError", "volcano"),
    "unknown scene in step": ({**_good_step(), "keys": ["nope"]},
                              "SceneError", "scene_key 'nope' is not loaded on this worker; loaded: \\["),
    "unknown scene in spawn": (SampleSpawn("nope", 1, 0.1, "uniform", (0, 0, 0), (1, 1, 1)).to_message(),
                               "SceneError", "'nope' is not loaded"),
    "unload unknown": (UnloadScene("nope").to_message(), "SceneError", "'nope' is not loaded"),
    "impossible spawn": (SampleSpawn("s0", 5, 50.0, "uniform", (0, 0, 0), (1, 1, 1)).to_message(), "SceneError", "clearance"),
}
UNKNOWN_SCENE_CASES = {"unknown scene in step", "unknown scene in spawn", "unload unknown"}
CODES = {name: "unknown_scene" if name in UNKNOWN_SCENE_CASES
         else "scene_missing" if name == "missing file"  # this worker's roots lack it: another worker may have it
         else {"ProtocolError": "bad_request", "SceneError": "scene_error"}[error_type]
         for name, (_, error_type, _) in MALFORMED.items()}


@pytest.mark.parametrize("name", list(MALFORMED))
def test_bad_request_gets_an_error_reply_and_the_worker_keeps_serving(worker, name):
    proc, session, _ = worker
    message, error_type, match = MALFORMED[name]
    ok, err = call(session, proc.rpc_key, message if isinstance(message, bytes) else encode(message))
    assert not ok
    assert err["type"] == "error" and err["error"] == error_type and err["code"] == CODES[name], err
    assert re.search(match, err["message"]), err["message"]
    ok, reply = _step(proc, session, _poses_at_origin(2))
    assert ok and split_step_result(reply)[0]["images"]["depth"].shape == (2, 1, 48, 64)
    assert proc.poll() is None


def test_shared_memory_is_used_only_when_asked(worker, request):
    proc, session, _ = worker
    ok, _ = _step(proc, session, _poses_at_origin(50))  # a 600 kB reply: over shared memory if enabled
    assert ok
    held = shm._zenoh_files_open_in(Path(f"/proc/{proc.pid}/fd"))
    assert bool(held) == ("shm" in request.node.callspec.id), held


def test_egl_worker_matches_in_process_egl(worker_factory):
    scene = resolve_source(SOURCE, [os.getcwd()])
    proc = worker_factory(RUN, backend="egl")
    poses = _poses(scene, 6, seed=5)
    with client_session(proc.endpoint) as session:
        ok, reply = call(session, proc.rpc_key, LoadScene("s0", SOURCE, CAMERAS, drone_radius=RADIUS).to_message())
        assert ok and reply["backend"] == "egl", reply
        ok, reply = _step(proc, session, poses)
        assert ok, reply
    with make_renderer("egl", scene, CAMERAS, drone_radius=RADIUS) as renderer:
        expected = renderer.render(poses.astype(np.float64))
    for name in ("depth", "seg"):
        np.testing.assert_array_equal(split_step_result(reply)[0]["images"][name], expected[name])
