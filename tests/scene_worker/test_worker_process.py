"""A real worker process under load: health keeps answering while a heavy scene loads, and a second
worker with a live worker's id refuses to start."""

from __future__ import annotations

import os
import re
import time

import numpy as np
import pytest
import zenoh

from tests.helpers import call, client_session, free_port, start_worker, stop_process
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.codec import decode, encode
from visfly_dist.protocol.messages import Health, LoadScene, ScenePoses, StepRequest

pytestmark = pytest.mark.worker

RUN = f"proc{os.getpid()}"
HEAVY = "gen:garage-stones?seed=11&density=0.8"   # about 1,000 stones: seconds of generation and BVH builds


def test_health_and_other_scenes_answer_while_a_heavy_scene_loads(worker_factory):
    """While one scene loads, the worker keeps answering: health (reporting the load), steps of another
    scene, and a typed refusal for the loading scene; then the load's own reply arrives. (How fast it
    answers is ``visfly-dist bench``'s business, not a unit test's.)"""
    proc = worker_factory(RUN)
    poses = np.array([[2.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]], np.float32)
    with client_session(proc.endpoint) as session:
        assert call(session, proc.rpc_key, LoadScene("light", "gen:empty", (CameraSpec(),)).to_message())[0]
        pending = session.get(proc.rpc_key, payload=encode(LoadScene("heavy", HEAVY, (CameraSpec(),)).to_message()),
                              timeout=120.0, consolidation=zenoh.ConsolidationMode.NONE)
        rounds_while_loading = 0
        while rounds_while_loading < 5:
            ok, health = call(session, proc.rpc_key, Health().to_message(), timeout=60.0)
            assert ok, health
            if health["loading"] != ["heavy"]:
                break  # the load is over
            ok, step = call(session, proc.rpc_key, StepRequest((ScenePoses("light", poses),)).to_message())
            assert ok and step["images"]["depth"].shape == (1, 1, 64, 64)
            ok, err = call(session, proc.rpc_key, StepRequest((ScenePoses("heavy", poses),)).to_message())
            assert not ok and err["code"] == "scene_loading", err
            rounds_while_loading += 1
            time.sleep(0.05)
        assert rounds_while_loading >= 1, ("no health answer came while the heavy scene loaded: the worker blocks "
                                           "on loads, or the load is too quick (choose a heavier scene)")
        (reply,) = list(pending)
        loaded = decode(reply.ok.payload.to_bytes())
        assert loaded["type"] == "scene_loaded" and loaded["metadata"]["num_stones"] == round(18 * 14 * 5 * 0.8)
        ok, health = call(session, proc.rpc_key, Health().to_message())
        assert health["scenes"] == ["heavy", "light"] and health["loading"] == []


def test_a_second_worker_with_a_live_worker_id_refuses_to_start(worker_factory, scene_root):
    first = worker_factory(RUN, worker_id="dup")
    with pytest.raises(RuntimeError, match="worker id 'dup' is already alive in run") as info:
        start_worker(RUN, f"tcp/127.0.0.1:{free_port()}", scene_root, worker_id="dup",
                     extra_args=["--connect", first.endpoint])
    assert "unique --worker-id" in str(info.value)
    with client_session(first.endpoint) as session:  # the first one is untouched
        ok, health = call(session, first.rpc_key, Health().to_message())
        assert ok and health["worker_id"] == "dup" and health["pid"] == first.pid


def test_a_restarted_worker_may_reuse_the_id_of_a_stopped_one(worker_factory, scene_root):
    first = worker_factory(RUN, worker_id="again")
    endpoint = first.endpoint
    assert stop_process(first) == 0
    second = start_worker(RUN, f"tcp/127.0.0.1:{endpoint.rsplit(':', 1)[1]}", scene_root, worker_id="again")
    try:
        with client_session(endpoint) as session:
            ok, health = call(session, second.rpc_key, Health().to_message())
            assert ok and health["pid"] == second.pid
    finally:
        stop_process(second)


def test_a_worker_at_its_memory_bound_refuses_loads_with_overloaded_and_keeps_serving(worker_factory):
    light = LoadScene("light", "gen:empty", (CameraSpec(),)).to_message()
    full = worker_factory(RUN, worker_id="mem-full", extra_args=["--max-memory-mb", "1"])
    with client_session(full.endpoint) as session:
        ok, err = call(session, full.rpc_key, light)
        assert not ok and err["code"] == "overloaded", err
        assert re.search(r"uses \d+ MB before loading, at or over its bound of 1 MB \(--max-memory-mb\)", err["message"])
        ok, health = call(session, full.rpc_key, Health().to_message())
        assert ok and health["scenes"] == [] and health["limits"]["max_memory_bytes"] == 1024 * 1024
        base_mb = health["memory_bytes"] // (1024 * 1024)
    # Room for a light scene, not for a heavy one (about 65 MB): the heavy one is dropped once built.
    roomy = worker_factory(RUN, worker_id="mem-roomy", extra_args=["--max-memory-mb", str(base_mb + 25)])
    with client_session(roomy.endpoint) as session:
        assert call(session, roomy.rpc_key, light)[0]
        ok, err = call(session, roomy.rpc_key, LoadScene("heavy", HEAVY, (CameraSpec(),)).to_message(), timeout=120)
        assert not ok and err["code"] == "overloaded", err
        assert "with scene 'gen:garage-stones" in err["message"] and "built" in err["message"]
        ok, health = call(session, roomy.rpc_key, Health().to_message())
        assert ok and health["scenes"] == ["light"] and health["loading"] == []
        poses = np.array([[2.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]], np.float32)
        assert call(session, roomy.rpc_key, StepRequest((ScenePoses("light", poses),)).to_message())[0]
