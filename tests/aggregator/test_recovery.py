"""Recovery without gaps: a worker whose request was lost comes back, and scenes the run never
learned of are unloaded. Real router, real remote worker processes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from tests.aggregator.conftest import CAMERAS, make_aggregator, spawn_poses
from tests.helpers import REPO, _read_line, free_port, start_worker, stop_process, wait_for
from visfly_dist.protocol.codec import decode, encode
from visfly_dist.protocol.messages import LoadScene
from visfly_dist.protocol.session import client_of, open_session

SCENES = {"sources": ("gen:pillars",), "num_scenes": 2, "agents_per_scene": 2}
HEAVY = "gen:garage-stones?density=0.8"  # seconds of generation: a load that is surely in flight


def _router(endpoint: str) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "visfly_dist.cli", "router", "--listen", endpoint], cwd=REPO,
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    assert "router ready" in _read_line(proc, 30.0)
    return proc


def _held(agg) -> dict[str, list[str]]:
    """worker -> scene keys it holds (or is loading), from its own health reply."""
    return {h["worker_id"]: sorted(h.get("scenes", []) + h.get("loading", [])) for h in agg.health()}


def _served(agg) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {w: [] for w in agg.workers}
    for s in agg.table.slots:
        if s.worker is not None:
            out.setdefault(s.worker, []).append(s.key)
        if s.incoming is not None:  # a swap armed: next episodes start there
            out.setdefault(s.incoming.move.worker, []).append(s.incoming.move.key)
    return {w: sorted(k) for w, k in out.items()}


@pytest.fixture
def router_endpoint():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = _router(endpoint)
    yield endpoint, proc
    stop_process(proc)


def test_a_remote_worker_that_missed_a_deadline_is_taken_back_once_it_answers(router_endpoint, scene_root):
    """Its token never goes (long lease), so no liveliness event would ever lift its ban."""
    endpoint, _ = router_endpoint
    args = ["--lease-ms", "10000"]
    a = start_worker("back", endpoint, scene_root, connect=True, worker_id="wa", extra_args=args)
    b = start_worker("back", endpoint, scene_root, connect=True, worker_id="wb", extra_args=args)
    try:
        with make_aggregator(pool={"connect": (endpoint,), "num_local_workers": 0, "run_id": "back", "min_workers": 2,
                                   "step_timeout_s": 1.0}, scenes=SCENES) as agg:
            poses = spawn_poses(agg)
            assert not agg.observe(poses).lost.any()
            assert sorted(agg.assignment().values()) == ["wa", "wb"]
            os.kill(a.pid, signal.SIGSTOP)  # misses the step deadline; its token stays (10 s lease)
            try:
                assert agg.observe(poses).lost.any()
                assert agg.workers == ["wb"]
            finally:
                os.kill(a.pid, signal.SIGCONT)
            assert wait_for(lambda: (agg.observe(poses), set(agg.assignment().values()) == {"wa", "wb"})[1],
                            timeout=30), (agg.workers, agg.assignment())
            # What it served before its ban was unloaded when it came back: it holds what it serves.
            assert wait_for(lambda: (agg.observe(poses), _held(agg) == _served(agg))[1], timeout=30), \
                (_held(agg), _served(agg))
            assert not agg.observe(poses).lost.any()
    finally:
        stop_process(a)
        stop_process(b)


def test_scenes_a_worker_loaded_without_the_run_knowing_are_unloaded_when_it_reappears(router_endpoint, scene_root):
    """A load whose reply was lost (a router killed while it was in flight) leaves a scene the run
    never learned of; when the worker is seen again after the outage, the run unloads it."""
    endpoint, router = router_endpoint
    w = start_worker("stray", endpoint, scene_root, connect=True, worker_id="ws", extra_args=["--lease-ms", "1000"])
    try:
        with make_aggregator(pool={"connect": (endpoint,), "num_local_workers": 0, "run_id": "stray",
                                   "step_timeout_s": 2.0, "outage_limit_s": 60.0}, scenes=SCENES) as agg:
            poses = spawn_poses(agg)
            assert not agg.observe(poses).lost.any()
            # The load the run sent for a move, answered into the void: a key of the run's own form.
            session = open_session(client_of([endpoint]))
            try:
                replies = list(session.get(w.rpc_key, payload=encode(LoadScene("s0v99", "gen:pillars", CAMERAS)
                                                                      .to_message()), timeout=30.0))
            finally:
                session.close()
            assert decode(replies[0].ok.payload.to_bytes())["type"] == "scene_loaded"
            assert "s0v99" in _held(agg)["ws"]
            assert stop_process(router) == 0  # an outage: the worker drops off and comes back
            router = _router(endpoint)
            assert wait_for(lambda: (agg.observe(poses), "s0v99" not in sum(_held(agg).values(), []))[1],
                            timeout=60), _held(agg)
            assert wait_for(lambda: (agg.observe(poses), _held(agg) == _served(agg))[1], timeout=30), \
                (_held(agg), _served(agg))
    finally:
        stop_process(w)
        stop_process(router)


def test_a_router_killed_while_a_load_is_in_flight_leaves_no_scene_behind(router_endpoint, scene_root):
    """The load's reply is lost with the router; the worker finishes the load anyway. Once the router
    is back, the run serves its scenes again and the worker holds exactly those."""
    endpoint, router = router_endpoint
    w = start_worker("inflight", endpoint, scene_root, connect=True, worker_id="wl", extra_args=["--lease-ms", "1000"])
    try:
        with make_aggregator(pool={"connect": (endpoint,), "num_local_workers": 0, "run_id": "inflight",
                                   "step_timeout_s": 2.0, "outage_limit_s": 60.0},
                             scenes={"sources": (HEAVY,), "num_scenes": 1, "agents_per_scene": 1,
                                     "swap_every_resets": 1}) as agg:
            poses = spawn_poses(agg)
            assert not agg.observe(poses).lost.any()
            agg.note_resets(np.array([0]))  # a swap: the next scene loads in the background (seconds)
            assert wait_for(lambda: any(h.get("loading") for h in agg.health()), timeout=30, interval=0.05)
            router.kill()  # the router dies with the load in flight
            router.wait()
            router = _router(endpoint)
            assert wait_for(lambda: (agg.observe(poses), agg.workers == ["wl"] and _held(agg) == _served(agg)
                                     and not any(h.get("loading") for h in agg.health()))[1], timeout=90), \
                (_held(agg), _served(agg))
            assert not agg.observe(poses).lost.any()
    finally:
        stop_process(w)
        stop_process(router)
