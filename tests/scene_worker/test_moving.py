"""Moving obstacles in the worker: every renderer and query backend against the static scene of the
same instant, batched renders at different times, spawns clear of swept paths, and real worker
processes (a replacement worker at the same time answers the same)."""

from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh

from tests.helpers import call, client_session
from visfly_dist.errors import ConfigError, ProtocolError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.messages import LoadScene, ScenePoses, StepRequest, parse_request, split_step_result, step_message
from visfly_dist.scene_worker import render_native
from visfly_dist.scene_worker.queries import ObstacleQueries
from visfly_dist.scene_worker.render_base import available_backends, make_renderer, render_scenes
from visfly_dist.scene_worker.render_raycast import RaycastRenderer
from visfly_dist.scenes import resolve_source, sample_free_positions
from visfly_dist.scenes.motion import Circle, Polygon, Spline, motion_from_dict
from visfly_dist.scenes.scene import MOVING_KEY, Scene, SceneObject

CAMERAS = (CameraSpec(name="depth", width=48, height=32), CameraSpec(name="seg", kind="segmentation", width=48, height=32))
RGB = CameraSpec(name="rgb", kind="rgb", width=48, height=32)
TOLERANCE_M = 1e-5
TIMES = (0.0, 1.3, 4.75, 11.2)
GEN_SOURCE = "gen:garage-stones?seed=2&density=0.03&moving=4"


def _box_scene() -> Scene:
    """A floor, a static wall, and three 0.6 m cubes on a circle, a polygon and a spline."""
    floor = trimesh.creation.box(extents=(20, 20, 0.1), transform=trimesh.transformations.translation_matrix([5, 0, -0.05]))
    wall = trimesh.creation.box(extents=(0.2, 8, 3), transform=trimesh.transformations.translation_matrix([9, 0, 1.5]))
    motions = [Circle([4.0, 0.0, 1.2], 1.5, 1.1, phase=0.4), Polygon([[3, -5, 1], [6, -5, 1.5], [6, -3.2, 1]], 0.8),
               Spline([[3, 2.6, 1], [5, 2.4, 1.4], [6, 4, 1], [4, 4.5, 1.2]], 1.4)]
    objects = [SceneObject("floor", 1, floor), SceneObject("wall", 2, wall)]
    for k, motion in enumerate(motions):
        cube = trimesh.creation.box(extents=(0.6, 0.6, 0.6))
        cube.visual.face_colors = [200, 40 * k, 30, 255]
        objects.append(SceneObject(f"cube{k}", 3 + k, cube, motion))
    return Scene("boxes", objects, np.array([[-2, -6, 0], [10, 6, 4]]))


def _looking_at(targets: np.ndarray, up: float = 2.5) -> np.ndarray:
    """Poses ``up`` metres above each target, looking straight down (face-on to the cubes' tops)."""
    down = [np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0]   # body +x turned to world -z
    return np.concatenate([targets + [0.0, 0.0, up], np.tile(down, (len(targets), 1))], axis=1)


def _poses_at(scene: Scene, t: float) -> np.ndarray:
    return _looking_at(np.stack([o.motion.position(t) for o in scene.moving_objects]))


def _backends() -> list[tuple[str, dict]]:
    out = []
    if render_native.available():
        out.append(("raycast", {"tracer": "native"}))
    out.append(("raycast", {"tracer": "embreex"}))
    if "egl" in available_backends():
        out.append(("egl", {}))
    return out


@pytest.mark.parametrize("backend, options", _backends(), ids=lambda v: v if isinstance(v, str) else v.get("tracer", ""))
def test_moving_render_matches_the_static_scene_of_the_same_instant(backend, options):
    scene = _box_scene()
    moving = make_renderer(backend, scene, CAMERAS + (RGB,), **options)
    ids = [o.object_id for o in scene.moving_objects]
    try:
        previous = None
        for t in TIMES:
            poses = _poses_at(scene, t)
            got = moving.render(poses, time=t)
            with make_renderer(backend, scene.at_time(t), CAMERAS + (RGB,), **options) as static:
                want = static.render(poses)
            np.testing.assert_allclose(got["depth"], want["depth"], rtol=0, atol=TOLERANCE_M)
            np.testing.assert_array_equal(got["seg"], want["seg"])
            assert np.abs(got["rgb"].astype(int) - want["rgb"]).mean() < 0.5   # same colours where they are
            for k, object_id in enumerate(ids):   # camera k sees cube k in the middle of its image
                assert got["seg"][k, 0, 16, 24] == object_id and got["rgb"][k, 0, 16, 24] > 100   # red
                assert got["depth"][k, 0, 16, 24] == pytest.approx(2.5 - 0.3, abs=TOLERANCE_M)
            if previous is not None:
                assert not np.array_equal(moving.render(previous[0], time=t)["seg"], previous[1])   # it moved
            previous = (poses, got["seg"])
    finally:
        moving.close()


@pytest.mark.parametrize("tracer", ["native", "embreex"])
def test_generated_moving_stones_match_the_static_scene(tracer):
    if tracer == "native" and not render_native.available():
        pytest.skip("native tracer not built")
    scene = resolve_source(GEN_SOURCE, [os.getcwd()])
    t = 6.4
    rng = np.random.default_rng(5)   # above each stone, and anywhere with any heading (tiles culled or not)
    yaw, pitch = rng.uniform(-np.pi, np.pi, 60), rng.uniform(-0.6, 0.6, 60)
    quats = np.stack([np.cos(yaw / 2) * np.cos(pitch / 2), -np.sin(yaw / 2) * np.sin(pitch / 2),
                      np.cos(yaw / 2) * np.sin(pitch / 2), np.sin(yaw / 2) * np.cos(pitch / 2)], axis=1)
    anywhere = np.concatenate([rng.uniform(scene.bounds[0] + 0.3, scene.bounds[1] - 0.3, (60, 3)), quats], axis=1)
    centres = np.stack([o.motion.position(t) for o in scene.moving_objects])
    inside = np.concatenate([centres + [0.05, 0.0, 0.0], quats[:len(centres)]], axis=1)   # a box behind the camera plane
    poses = np.concatenate([_poses_at(scene, t), anywhere, inside])
    with RaycastRenderer(scene, CAMERAS, tracer=tracer) as moving, RaycastRenderer(scene.at_time(t), CAMERAS, tracer=tracer) as static:
        got, want = moving.render(poses, time=t), static.render(poses)
    # grazing hits far away may differ by a few float32 steps of the depth (1.9e-6 m at 16 m)
    np.testing.assert_allclose(got["depth"], want["depth"], rtol=2e-6, atol=TOLERANCE_M)
    assert (np.abs(got["depth"] - want["depth"]) <= TOLERANCE_M).mean() > 0.9999
    assert (got["seg"] == want["seg"]).mean() > 0.999   # a pixel centre on an edge may round either way
    assert np.isin(got["seg"], [o.object_id for o in scene.moving_objects]).any()


def test_render_scenes_places_each_item_at_its_own_time():
    scene = _box_scene()
    times = [0.5, 3.0, 7.5]
    renderers = [make_renderer("raycast", scene, CAMERAS) for _ in range(2)]
    try:
        items = [(renderers[0], _poses_at(scene, times[0]), False, times[0]),
                 (renderers[1], _poses_at(scene, times[1]), False, times[1]),
                 (renderers[0], _poses_at(scene, times[2]), False, times[2])]   # the same renderer, later
        results = render_scenes(items)
        for (_, poses, _, t), result in zip(items, results):
            with make_renderer("raycast", scene.at_time(t), CAMERAS) as static:
                want = static.render(poses)
            np.testing.assert_allclose(result["depth"], want["depth"], rtol=0, atol=TOLERANCE_M)
            np.testing.assert_array_equal(result["seg"], want["seg"])
        with pytest.raises(ConfigError, match="time=nan must be a finite number"):
            renderers[0].render(_poses_at(scene, 0.0), time=float("nan"))
        with pytest.raises(ConfigError, match="time='1' must be a finite number"):   # checked before any render
            render_scenes([(renderers[0], _poses_at(scene, 0.0), False, 0.0), (renderers[1], _poses_at(scene, 0.0), False, "1")])
        with pytest.raises(ConfigError, match="time=inf must be a finite number"):
            ObstacleQueries(scene).query(np.zeros((1, 3)), 1.0, time=float("inf"))
    finally:
        for r in renderers:
            r.close()


@pytest.mark.parametrize("backend", ["native", "fcl"])
def test_moving_queries_match_the_static_scene_of_the_same_instant(backend):
    if backend == "native" and not render_native.available():
        pytest.skip("native library not built")
    scene = _box_scene()
    queries = ObstacleQueries(scene, drone_radius=0.1, backend=backend)
    rng = np.random.default_rng(3)
    for t in TIMES:
        centres = np.stack([o.motion.position(t) for o in scene.moving_objects])
        positions = np.concatenate([c + rng.normal(0.0, 0.35, (40, 3)) for c in centres]
                                   + [rng.uniform(scene.bounds[0], scene.bounds[1], (60, 3))])
        got = queries.query(positions, 3.0, time=t)
        want = ObstacleQueries(scene.at_time(t), drone_radius=0.1, backend=backend).query(positions, 3.0)
        np.testing.assert_allclose(got.distance, want.distance, rtol=0, atol=TOLERANCE_M)
        np.testing.assert_allclose(got.nearest, want.nearest, rtol=0, atol=TOLERANCE_M)
        np.testing.assert_array_equal(got.inside, want.inside)
        np.testing.assert_array_equal(got.collision, want.collision)
        assert got.inside.sum() >= 10   # some positions are inside the cubes (0.3 m half side)
        inside_cube = np.abs(positions[:, None, :] - centres[None]).max(axis=2).min(axis=1) < 0.299
        clear = np.abs(positions[:, None, :] - centres[None]).max(axis=2).min(axis=1) > 0.301
        in_floor = positions[:, 2] < 0.0
        np.testing.assert_array_equal(got.inside[inside_cube], True)
        np.testing.assert_array_equal(got.inside[clear & ~in_floor & (positions[:, 0] < 8.8)], False)


def test_spawns_keep_clear_of_the_swept_paths():
    scene = _box_scene()
    queries = ObstacleQueries(scene, drone_radius=0.1)
    clearance = 0.4
    spawns = sample_free_positions(300, clearance, "uniform", [1, -4, 0.5], [8, 4, 2.5], np.random.default_rng(0),
                                   queries.distance, bounds=scene.bounds)
    for t in np.linspace(0.0, 60.0, 241):   # wherever a cube is, no spawn is within the clearance of it
        placed = ObstacleQueries(scene.at_time(t), drone_radius=0.1)
        assert placed.query(spawns, 5.0).distance.min() >= clearance - 0.03
    on_path = np.stack([o.motion.position(2.0) for o in scene.moving_objects])
    assert np.all(queries.distance(on_path) < 0)


def test_step_times_travel_on_the_wire_and_are_validated():
    poses = np.tile([1.0, 0, 1, 1, 0, 0, 0], (2, 1))
    msg = StepRequest((ScenePoses("a", poses[:1], 2.5), ScenePoses("b", poses[1:]))).to_message()
    assert msg["times"].dtype == np.float64 and msg["times"].tolist() == [2.5, 0.0]
    assert [s.time for s in parse_request(msg).scenes] == [2.5, 0.0]
    assert "times" not in StepRequest((ScenePoses("a", poses),)).to_message()
    assert parse_request(StepRequest((ScenePoses("a", poses),)).to_message()).scenes[0].time == 0.0
    base = step_message(["a", "b"], np.array([1, 1]), poses)
    with pytest.raises(ProtocolError, match=r"times must be a float array of shape \(2,\)"):
        parse_request({**base, "times": np.zeros(3)})
    with pytest.raises(ProtocolError, match="times must be a float array"):
        parse_request({**base, "times": [0.0, 1.0]})
    with pytest.raises(ProtocolError, match="times must be finite seconds"):
        parse_request({**base, "times": np.array([0.0, np.inf])})
    with pytest.raises(ProtocolError, match="times must be finite seconds"):
        parse_request({**base, "times": np.array([np.nan, 0.0])})
    with pytest.raises(ProtocolError, match="times must be finite seconds"):
        parse_request({**base, "times": np.array([0.0, -2e9])})


@pytest.mark.worker
def test_a_replacement_worker_at_the_same_time_answers_the_same(worker_factory):
    from tests.helpers import stop_process

    scene = resolve_source(GEN_SOURCE, [os.getcwd()])
    t = 7.25
    poses = _poses_at(scene, t).astype(np.float32)
    request = StepRequest((ScenePoses("m", poses, t), ScenePoses("m", poses, 0.0)), search_radius=3.0).to_message()
    replies = []
    for attempt in range(2):
        proc = worker_factory(f"mov{os.getpid()}x{attempt}")
        with client_session(proc.endpoint) as session:
            ok, loaded = call(session, proc.rpc_key, LoadScene("m", GEN_SOURCE, CAMERAS).to_message())
            assert ok, loaded
            ok, reply = call(session, proc.rpc_key, request)
            assert ok, reply
        stop_process(proc)
        replies.append(split_step_result(reply))
        listed = loaded["metadata"][MOVING_KEY]   # the client computes the same positions locally
        assert [m["object_id"] for m in listed] == [o.object_id for o in scene.moving_objects]
        for m, obj in zip(listed, scene.moving_objects):
            np.testing.assert_array_equal(motion_from_dict(m["motion"]).position(t), obj.motion.position(t))
    (first_t, first_0), (second_t, second_0) = replies
    for a, b in ((first_t, second_t), (first_0, second_0)):
        for name in ("depth", "seg"):
            np.testing.assert_array_equal(a["images"][name], b["images"][name])
        for key in ("distance", "nearest", "collision", "inside"):
            np.testing.assert_array_equal(a[key], b[key])
    with make_renderer("raycast", scene.at_time(t), CAMERAS) as static:
        want = static.render(poses.astype(np.float64))
    np.testing.assert_allclose(first_t["images"]["depth"], want["depth"], rtol=0, atol=TOLERANCE_M)
    assert not np.array_equal(first_t["images"]["seg"], first_0["images"]["seg"])   # entries at their own times
    want_q = ObstacleQueries(scene.at_time(t), drone_radius=0.1).query(poses[:, :3].astype(np.float64), 3.0)
    np.testing.assert_allclose(first_t["distance"], want_q.distance, rtol=0, atol=TOLERANCE_M)
