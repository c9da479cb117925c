"""A worker's bounds and its load path, in-process through ``SceneWorker.submit``/``handle``: loads
run off the serving thread, every bound gives a typed error reply with its code."""

from __future__ import annotations

import os
import re
import threading

import numpy as np
import pytest

from visfly_dist.errors import ConfigError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.codec import decode, encode
from visfly_dist.protocol.messages import Health, LoadScene, ScenePoses, StepRequest, UnloadScene
from visfly_dist.protocol.session import SessionConfig
from visfly_dist.scene_worker.limits import WorkerLimits
from visfly_dist.scene_worker.service import SceneWorker

CAMERA = CameraSpec(name="depth", width=16, height=12)


@pytest.fixture
def make_worker(scene_root):
    workers = []

    def make(**limits) -> SceneWorker:
        worker = SceneWorker("bounds", SessionConfig(), [scene_root], backend="raycast", worker_id="w0",
                             limits=WorkerLimits(**limits))
        workers.append(worker)
        return worker

    yield make
    for worker in workers:
        worker.close()


def _call(worker: SceneWorker, message: dict) -> tuple[bool, dict]:
    ok, body = worker.handle(encode(message))
    return ok, decode(body)


def _load(key: str, source: str = "gen:empty") -> dict:
    return LoadScene(key, source, (CAMERA,)).to_message()


def _step(key: str, n: int = 2) -> dict:
    poses = np.zeros((n, 7), np.float32)
    poses[:, 2], poses[:, 3] = 1.0, 1.0
    return StepRequest((ScenePoses(key, poses),)).to_message()


def _error(worker: SceneWorker, message: dict) -> tuple[str, str, str]:
    ok, err = _call(worker, message)
    assert not ok, err
    return err["error"], err["code"], err["message"]


def test_scene_count_is_bounded_but_a_reload_of_a_held_key_is_not(make_worker):
    worker = make_worker(max_scenes=2)
    assert _call(worker, _load("a"))[0] and _call(worker, _load("b"))[0]
    error, code, message = _error(worker, _load("c"))
    assert (error, code) == ("SceneError", "overloaded") and "holds 2 scenes" in message and "--max-scenes" in message
    assert _call(worker, _load("b", "gen:pillars?seed=1"))[0]
    assert _call(worker, UnloadScene("a").to_message())[0] and _call(worker, _load("c"))[0]


def test_key_length_is_bounded(make_worker):
    worker = make_worker(max_key_chars=8)
    assert _call(worker, _load("k" * 8))[0]
    error, code, message = _error(worker, _load("k" * 9))
    assert (error, code) == ("ProtocolError", "too_large") and "--max-key-chars" in message


def test_pixels_per_step_are_bounded(make_worker):
    worker = make_worker(max_pixels=3 * 16 * 12)
    assert _call(worker, _load("s0"))[0]
    ok, reply = _call(worker, _step("s0", 3))
    assert ok and reply["images"]["depth"].shape == (3, 1, 12, 16)
    error, code, message = _error(worker, _step("s0", 4))
    assert (error, code) == ("ProtocolError", "too_large") and "768 pixels" in message
    ok, reply = _call(worker, {**_step("s0", 4), "render": False})  # queries only: no pixels
    assert ok and reply["distance"].shape == (4,)


@pytest.mark.parametrize("source, match", [
    ("gen:garage-stones?density=1e300", "must lie in"),
    ("gen:garage-stones?density=3", r"density=3.0 must be in \[0, 1.0\]"),
    ("gen:garage-stones?max_radius=50", "max_radius=50.0"),
    ("gen:pillars?density=100", "density=100.0 must be in"),
    ("gen:gap-walls?gap_width=-1e308", "must lie in"),
])
def test_generator_params_out_of_range_are_scene_errors(make_worker, source, match):
    worker = make_worker()
    error, code, message = _error(worker, _load("s0", source))
    assert (error, code) == ("SceneError", "scene_error")
    assert re.search(match, message), message


def test_a_step_on_a_loading_key_is_refused_until_the_load_is_answered(make_worker):
    worker = make_worker()
    assert _call(worker, _load("old"))[0]
    answers = []
    worker.submit(encode(_load("new", "gen:pillars?seed=3")), lambda ok, body: answers.append((ok, decode(body))))
    worker.submit(encode(_load("old", "gen:pillars?seed=4")), lambda ok, body: answers.append((ok, decode(body))))
    assert answers == []  # both loads run in the background
    assert _error(worker, _step("new"))[:2] == ("SceneError", "scene_loading")
    assert _error(worker, _load("new"))[:2] == ("SceneError", "scene_loading")
    assert _call(worker, _step("old"))[0]  # a key being re-loaded keeps serving its old scene
    health = _call(worker, Health().to_message())[1]
    assert health["loading"] == ["new", "old"] and health["scenes"] == ["old"]
    while len(answers) < 2:
        worker._serve_one(0.1)
    assert [(ok, r["scene_key"]) for ok, r in answers] == [(True, "new"), (True, "old")]
    assert _call(worker, _step("new"))[0]
    assert _call(worker, Health().to_message())[1]["loading"] == []


def test_unload_cancels_a_load_in_progress(make_worker):
    worker = make_worker()
    answers = []
    worker.submit(encode(_load("s0", "gen:pillars?seed=5")), lambda ok, body: answers.append((ok, decode(body))))
    assert _call(worker, UnloadScene("s0").to_message())[0]
    assert len(answers) == 1 and not answers[0][0] and answers[0][1]["code"] == "unknown_scene"
    assert "cancelled by unload_scene" in answers[0][1]["message"]
    worker._serve_one(30.0)  # the finished load is discarded, not installed
    assert _error(worker, _step("s0"))[:2] == ("SceneError", "unknown_scene")


def test_close_answers_loads_in_progress_with_shutting_down(make_worker):
    worker = make_worker()
    answers = []
    worker.submit(encode(_load("s0", "gen:pillars?seed=6")), lambda ok, body: answers.append((ok, decode(body))))
    worker.close()
    assert len(answers) == 1 and answers[0][1]["error"] == "WorkerShutdown"
    assert answers[0][1]["code"] == "shutting_down"


@pytest.mark.parametrize("kwargs", [{"max_scenes": 0}, {"max_key_chars": 257}, {"max_pixels": True},
                                    {"max_pixels": 1.5}])
def test_limits_refuse_bad_values(kwargs):
    with pytest.raises(ConfigError, match=f"{next(iter(kwargs))}="):
        WorkerLimits(**kwargs)


def test_a_repeated_step_sees_scenes_unloaded_reloaded_and_re_cameraed_in_between(make_worker):
    """The worker remembers the last step's scenes; any load or unload in between is seen."""
    worker = make_worker()
    assert _call(worker, _load("a"))[0] and _call(worker, _load("b"))[0]
    poses = np.zeros((2, 7), np.float32)
    poses[:, 2], poses[:, 3] = 1.0, 1.0
    both = StepRequest((ScenePoses("a", poses), ScenePoses("b", poses))).to_message()
    assert _call(worker, both)[0] and _call(worker, both)[0]
    assert _call(worker, UnloadScene("b").to_message())[0]
    assert _error(worker, both)[:2] == ("SceneError", "unknown_scene")
    wide = CameraSpec(name="depth", width=32, height=12)
    assert _call(worker, LoadScene("b", "gen:empty", (wide,)).to_message())[0]
    assert _error(worker, both) == ("ProtocolError", "bad_request",
                                    "the scenes of one step request must carry the same cameras")
    assert _call(worker, _load("b"))[0]
    ok, reply = _call(worker, both)
    assert ok and reply["counts"].tolist() == [2, 2] and reply["images"]["depth"].shape == (4, 1, 12, 16)


def test_loads_after_the_first_step_run_below_the_serving_thread(make_worker, monkeypatch):
    """Start-up loads keep the worker's priority; loads that arrive while steps are served (swaps,
    rebalancing) run niced, so generating a scene does not slow the steps' rendering."""
    from visfly_dist.scene_worker import loads

    niceness = {}
    prepare = loads.prepare_scene

    def recording(request, *args):
        niceness[request.scene_key] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        return prepare(request, *args)

    own = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    if own >= loads.BACKGROUND_LOAD_NICE:
        pytest.skip(f"the tests already run at niceness {own}")
    monkeypatch.setattr(loads, "prepare_scene", recording)
    worker = make_worker()
    assert _call(worker, _load("before"))[0]
    ok, reply = _call(worker, StepRequest((ScenePoses("before", np.array([[1, 0, 1, 1, 0, 0, 0]], np.float32)),)).to_message())
    assert ok, reply
    assert _call(worker, _load("after", "gen:pillars?seed=1"))[0]  # another source: built (one already held is shared)
    assert niceness == {"before": own, "after": loads.BACKGROUND_LOAD_NICE}


def test_one_file_over_many_keys_is_built_once_and_shared_until_its_last_key_goes(make_worker, scene_root):
    import trimesh

    trimesh.creation.box((1.0, 1.0, 2.0), trimesh.transformations.translation_matrix((3, 0, 1))).export(
        scene_root / "shared_box.ply")
    worker = make_worker()
    assert _call(worker, _load("a", "shared_box.ply"))[0]
    ok, reply = _call(worker, _load("b", "shared_box.ply"))  # a second slot of the same file
    assert ok and reply["scene_key"] == "b" and reply["num_triangles"] == 12
    a, b = worker._scenes.get("a"), worker._scenes.get("b")
    assert b.renderer is a.renderer and b.queries is a.queries and b.scene is a.scene  # built once
    other = _load("c", "shared_box.ply")
    other["drone_radius"] = 0.3  # other queries: built anew
    assert _call(worker, other)[0] and worker._scenes.get("c").queries is not a.queries
    ok_a, step_a = _call(worker, _step("a"))
    assert _call(worker, UnloadScene("a").to_message())[0]  # b still serves, its renderer open
    ok_b, step_b = _call(worker, _step("b"))
    assert ok_a and ok_b and np.array_equal(step_a["images"]["depth"], step_b["images"]["depth"])
    assert np.array_equal(step_a["distance"], step_b["distance"])
    assert _call(worker, UnloadScene("b").to_message())[0]
    assert _call(worker, _load("d", "shared_box.ply"))[0]  # the last key gone: built again
    assert worker._scenes.get("d").renderer is not a.renderer


def test_loads_of_one_file_that_arrive_together_build_it_once(make_worker, scene_root):
    """A start-up's burst: every slot of a one-file dataset asks at once; the first builds, the others wait
    for it and share it; one unloaded while it waits is answered as cancelled and the rest go on."""
    import time

    import trimesh

    trimesh.creation.icosphere(subdivisions=4).export(scene_root / "burst.ply")
    worker = make_worker()
    answers: dict[str, tuple[bool, dict]] = {}
    for key in ("k0", "k1", "k2", "k3"):
        worker.submit(encode(_load(key, "burst.ply")), lambda ok, body, key=key: answers.__setitem__(key, (ok, decode(body))))
    worker.submit(encode(UnloadScene("k2").to_message()), lambda ok, body: answers.__setitem__("unload", (ok, decode(body))))
    deadline = time.monotonic() + 60
    while len(answers) < 5 and time.monotonic() < deadline:
        worker._serve_one(0.05)
    assert answers["unload"][0] and not answers["k2"][0] and "cancelled" in answers["k2"][1]["message"]
    assert all(answers[k][0] and answers[k][1]["num_triangles"] == 5120 for k in ("k0", "k1", "k3"))
    scenes = [worker._scenes.get(k) for k in ("k0", "k1", "k3")]
    assert all(s.renderer is scenes[0].renderer and s.queries is scenes[0].queries for s in scenes)
    assert worker._scenes.keys() == ["k0", "k1", "k3"] and not worker._scenes.loading_keys()


def test_loads_of_a_missing_file_that_arrive_together_are_each_answered_with_its_error(make_worker):
    """A burst of loads of one scene whose build fails: every load is answered with the error and
    none stays loading (the waiters used to wait on one another for ever)."""
    import time

    worker = make_worker()
    answers: dict[str, tuple[bool, dict]] = {}
    keys = ("m0", "m1", "m2", "m3")
    for key in keys:
        worker.submit(encode(_load(key, "no_such_dir/missing.ply")),
                      lambda ok, body, key=key: answers.__setitem__(key, (ok, decode(body))))
    deadline = time.monotonic() + 30
    while len(answers) < len(keys) and time.monotonic() < deadline:
        worker._serve_one(0.05)
    assert sorted(answers) == list(keys), f"unanswered: {sorted(set(keys) - set(answers))}"
    assert all(not ok and reply["code"] == "scene_missing" and "missing.ply" in reply["message"]
               for ok, reply in answers.values())
    assert not worker._scenes.loading_keys() and not worker._scenes.keys()
