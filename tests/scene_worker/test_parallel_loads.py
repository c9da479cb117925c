"""A real worker with a thread share of 2 under bursts of loads (a start-up placement): every load gets
its one correct reply, generated scenes are made in child processes, the memory bound still refuses
cleanly, steps and unloads in between are answered, and no child outlives the start-up or the worker."""

from __future__ import annotations

import os
import signal
from typing import Any

import numpy as np
import pytest
import zenoh

from tests.helpers import call, client_session, wait_for
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.codec import decode, encode
from visfly_dist.protocol.messages import Health, LoadScene, ScenePoses, StepRequest, UnloadScene
from visfly_dist.scene_worker.loads import CHILDREN_AFTER
from visfly_dist.scenes import resolve_source

pytestmark = pytest.mark.worker

RUN = f"ploads{os.getpid()}"
BURST = CHILDREN_AFTER + 2   # generated loads sent at once: enough to start the generator processes
THREADS = ["--threads", "2"]
POSE = np.array([[2.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]], np.float32)


def _spec(i: int, density: float = 0.15) -> str:
    return f"gen:garage-stones?seed={i}&density={density}"


def _load(key: str, source: str) -> dict[str, Any]:
    return LoadScene(key, source, (CameraSpec(),)).to_message()


def _send(session: Any, key: str, message: dict[str, Any]) -> Any:
    """Send without waiting; :func:`_answer` takes the reply."""
    return session.get(key, payload=encode(message), timeout=180.0, consolidation=zenoh.ConsolidationMode.NONE)


def _answer(pending: Any) -> tuple[bool, dict]:
    (reply,) = list(pending)
    if reply.ok is not None:
        return True, decode(reply.ok.payload.to_bytes())
    return False, decode(reply.err.payload.to_bytes())


def _burst(session: Any, key: str, sources: dict[str, str]) -> dict[str, Any]:
    return {k: _send(session, key, _load(k, source)) for k, source in sources.items()}


def _generators(pid: int) -> list[int]:
    """The worker's scene generator processes (spawned children; not multiprocessing's resource tracker)."""
    found = []
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{task}/children") as f:
                kids = f.read().split()
        except FileNotFoundError:  # the thread ended
            continue
        for kid in kids:
            try:
                with open(f"/proc/{kid}/cmdline", "rb") as f:
                    if b"spawn_main" in f.read():
                        found.append(int(kid))
            except FileNotFoundError:
                continue
    return found


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def _assert_is(reply: dict, key: str, source: str, scene_root) -> None:
    """``reply`` is the ``scene_loaded`` of ``source`` under ``key``, as this process generates it."""
    expected = resolve_source(source, [scene_root])
    assert reply["type"] == "scene_loaded" and reply["scene_key"] == key
    assert reply["num_triangles"] == expected.num_triangles and reply["num_objects"] == len(expected.objects)
    assert np.array_equal(reply["bounds"], expected.bounds)
    assert reply["metadata"]["num_stones"] == expected.metadata["num_stones"]


def _assert_all_loaded(session, proc, pending, sources, scene_root) -> None:
    """Every load of the burst answered with its own scene, and the worker holds exactly those."""
    for key, source in sources.items():
        ok, reply = _answer(pending[key])
        assert ok, reply
        _assert_is(reply, key, source, scene_root)
    ok, health = call(session, proc.rpc_key, Health().to_message())
    assert health["scenes"] == sorted(sources) and health["loading"] == []


def test_a_burst_of_loads_gets_one_correct_reply_each_and_generates_in_children(worker_factory, scene_root):
    proc = worker_factory(RUN, worker_id="burst", extra_args=THREADS)
    sources = {f"k{i}": _spec(i) for i in range(BURST)}
    with client_session(proc.endpoint) as session:
        pending = _burst(session, proc.rpc_key, sources)
        _assert_all_loaded(session, proc, pending, sources, scene_root)
        assert _generators(proc.pid), "a burst of generated loads should have started generator processes"
        # The children stay until the first step; once they are ready, loads are generated there.
        extra: list[str] = []

        def generated_in_child() -> bool:
            key = f"x{len(extra)}"
            extra.append(key)
            ok, reply = call(session, proc.rpc_key, _load(key, _spec(100 + len(extra))), timeout=120.0)
            assert ok, reply
            _assert_is(reply, key, _spec(100 + len(extra)), scene_root)
            timings = call(session, proc.rpc_key, Health().to_message())[1]["timings"]
            return timings.get("generate_in_child", {}).get("count", 0) > 0

        assert wait_for(generated_in_child, timeout=120.0, interval=0.2)
        ok, step = call(session, proc.rpc_key, StepRequest((ScenePoses(extra[-1], POSE),)).to_message())
        assert ok and step["images"]["depth"].shape == (1, 1, 64, 64)
        assert wait_for(lambda: not _generators(proc.pid), timeout=30.0), "the children should exit at the first step"


def test_the_memory_bound_refuses_cleanly_with_several_loads_in_flight(worker_factory):
    light = _load("light", "gen:empty")
    probe = worker_factory(RUN, worker_id="mem-probe", extra_args=THREADS)
    with client_session(probe.endpoint) as session:
        assert call(session, probe.rpc_key, light)[0]
        base_mb = call(session, probe.rpc_key, Health().to_message())[1]["memory_bytes"] // (1024 * 1024)
    # Room for about two garages of density 0.3 (about 20 MB each), not for the burst.
    proc = worker_factory(RUN, worker_id="mem-burst", extra_args=[*THREADS, "--max-memory-mb", str(base_mb + 60)])
    sources = {f"k{i}": _spec(i, 0.3) for i in range(BURST)}
    with client_session(proc.endpoint) as session:
        assert call(session, proc.rpc_key, light)[0]
        pending = _burst(session, proc.rpc_key, sources)
        answers = {key: _answer(p) for key, p in pending.items()}
        loaded = sorted(k for k, (ok, _) in answers.items() if ok)
        refused = [reply for ok, reply in answers.values() if not ok]
        assert loaded and refused, answers
        assert all((r["error"], r["code"]) == ("SceneError", "overloaded") for r in refused), refused
        assert all("--max-memory-mb" in r["message"] for r in refused)
        ok, health = call(session, proc.rpc_key, Health().to_message())
        assert health["scenes"] == sorted(["light", *loaded]) and health["loading"] == []
        for key in [*loaded, "light"]:
            ok, step = call(session, proc.rpc_key, StepRequest((ScenePoses(key, POSE),)).to_message())
            assert ok, step
        refused_key = next(k for k, (ok, _) in answers.items() if not ok)
        ok, err = call(session, proc.rpc_key, StepRequest((ScenePoses(refused_key, POSE),)).to_message())
        assert not ok and err["code"] == "unknown_scene"


def test_a_step_between_loads_is_answered_and_the_loads_still_complete(worker_factory, scene_root):
    proc = worker_factory(RUN, worker_id="step-between", extra_args=THREADS)
    sources = {f"k{i}": _spec(i) for i in range(BURST)}
    with client_session(proc.endpoint) as session:
        assert call(session, proc.rpc_key, _load("light", "gen:empty"))[0]
        pending = _burst(session, proc.rpc_key, sources)
        ok, step = call(session, proc.rpc_key, StepRequest((ScenePoses("light", POSE),)).to_message())
        assert ok and step["images"]["depth"].shape == (1, 1, 64, 64) and step["distance"].shape == (1,)
        ok, health = call(session, proc.rpc_key, Health().to_message())
        loading = health["loading"]
        assert loading and set(loading) <= set(sources), health   # the last ones are still in flight
        ok, err = call(session, proc.rpc_key, StepRequest((ScenePoses(loading[-1], POSE),)).to_message())
        if not ok:  # (answered if its load ended in between)
            assert (err["error"], err["code"]) == ("SceneError", "scene_loading"), err
        for key, source in sources.items():
            ok, reply = _answer(pending[key])
            assert ok, reply
            _assert_is(reply, key, source, scene_root)
        ok, health = call(session, proc.rpc_key, Health().to_message())
        assert health["scenes"] == sorted(["light", *sources]) and health["loading"] == []
        assert wait_for(lambda: not _generators(proc.pid), timeout=30.0), "the children should exit once steps are served"


def test_an_unload_during_a_burst_cancels_that_load_only(worker_factory, scene_root):
    proc = worker_factory(RUN, worker_id="unload-burst", extra_args=THREADS)
    sources = {f"k{i}": _spec(i) for i in range(BURST)}
    cancelled = ["k1", f"k{BURST - 1}"]
    with client_session(proc.endpoint) as session:
        pending = _burst(session, proc.rpc_key, sources)
        for key in cancelled:
            ok, reply = call(session, proc.rpc_key, UnloadScene(key).to_message())
            assert ok and reply["type"] == "ok"
        for key, source in sources.items():
            ok, reply = _answer(pending[key])
            if key in cancelled:
                assert not ok and reply["code"] == "unknown_scene" and "cancelled by unload_scene" in reply["message"]
            else:
                assert ok, reply
                _assert_is(reply, key, source, scene_root)
        ok, health = call(session, proc.rpc_key, Health().to_message())
        assert health["scenes"] == sorted(set(sources) - set(cancelled)) and health["loading"] == []
        ok, err = call(session, proc.rpc_key, StepRequest((ScenePoses("k1", POSE),)).to_message())
        assert not ok and err["code"] == "unknown_scene"
        ok, reply = call(session, proc.rpc_key, _load("k1", sources["k1"]), timeout=120.0)
        assert ok
        _assert_is(reply, "k1", sources["k1"], scene_root)


def test_a_generator_process_that_dies_loses_no_load(worker_factory, scene_root):
    proc = worker_factory(RUN, worker_id="child-dies", extra_args=THREADS)
    sources = {f"k{i}": _spec(i) for i in range(BURST)}
    with client_session(proc.endpoint) as session:
        pending = _burst(session, proc.rpc_key, sources)
        assert wait_for(lambda: bool(_generators(proc.pid)), timeout=30.0)
        os.kill(_generators(proc.pid)[0], signal.SIGKILL)
        _assert_all_loaded(session, proc, pending, sources, scene_root)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_the_generator_processes_exit_with_the_worker(worker_factory, sig):
    proc = worker_factory(RUN, worker_id=f"exits-{sig.name}", extra_args=THREADS)
    with client_session(proc.endpoint) as session:
        pending = _burst(session, proc.rpc_key, {f"k{i}": _spec(i) for i in range(BURST)})
        assert wait_for(lambda: bool(_generators(proc.pid)), timeout=30.0)
        children = _generators(proc.pid)
        os.kill(proc.pid, sig)
        assert proc.wait(30.0) == (0 if sig == signal.SIGTERM else -signal.SIGKILL), proc.stderr_text()[-3000:]
        del pending
    assert wait_for(lambda: not any(_alive(c) for c in children), timeout=30.0), "orphaned generator processes"
