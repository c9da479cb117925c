"""Pools behind a router: runs stay apart, remote workers join, TCP without shared memory, launch CLI."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tests.aggregator.conftest import make_aggregator, pid_alive, reference, spawn_poses
from tests.helpers import REPO, _read_line, free_port, start_worker, stop_process, wait_for
from visfly_dist.errors import NoWorkersError

SCENES = {"sources": ("gen:garage-stones",), "num_scenes": 2, "agents_per_scene": 2}


def _start_cli(*args: str) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-m", "visfly_dist.cli", *args], cwd=REPO,
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    line = _read_line(proc, 30.0)
    if not line:
        stop_process(proc)
        raise RuntimeError(f"visfly-dist {args[0]} printed no ready line")
    return proc, line


@pytest.fixture(scope="module")
def router():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc, line = _start_cli("router", "--listen", endpoint)
    assert "router ready" in line
    yield endpoint
    assert stop_process(proc) == 0  # closes cleanly on SIGTERM


def test_runs_on_one_router_stay_apart_without_shared_memory(router, scene_root):
    remote = start_worker("run-b", router, scene_root, connect=True, shm=False, worker_id="remote-b")
    a = make_aggregator(pool={"connect": (router,), "num_local_workers": 1, "run_id": "run-a", "shared_memory": False},
                        scenes=SCENES)
    b = make_aggregator(pool={"connect": (router,), "num_local_workers": 1, "run_id": "run-b", "shared_memory": False,
                              "min_workers": 2},
                        scenes=SCENES)
    try:
        a.start()
        b.start()
        assert a.workers == ["local-0"]
        assert b.workers == ["local-0", "remote-b"]
        assert sorted(b.assignment().values()) == ["local-0", "remote-b"]
        assert {h["pid"] for h in a.health()} == {a.local_worker_pids()["local-0"]}
        # one step's requests go to both: the local worker's on its channel, the remote one's through Zenoh
        assert {h["worker_id"]: h["transport"] for h in b.health()} == {"local-0": "channel", "remote-b": "zenoh"}
        for agg in (a, b):
            poses = spawn_poses(agg)
            obs = agg.observe(poses)
            np.testing.assert_allclose(obs.images["depth"], reference(agg, poses)["depth"], atol=1e-4)
    finally:
        a.close()
        b.close()
        stop_process(remote)


def test_a_replacement_skips_a_local_id_a_remote_worker_took(router, scene_root):
    agg = make_aggregator(pool={"connect": (router,), "num_local_workers": 1, "run_id": "run-ids", "respawn": True},
                          scenes=SCENES)
    remote = None
    try:
        agg.start()
        remote = start_worker("run-ids", router, scene_root, connect=True, worker_id="local-1")  # the next local id
        assert wait_for(lambda: "local-1" in agg.workers, timeout=30)
        os.kill(agg.local_worker_pids()["local-0"], signal.SIGKILL)
        poses = spawn_poses(agg)
        assert wait_for(lambda: (agg.observe(poses), "local-2" in agg.workers)[1], timeout=30), agg.workers
        assert sorted(agg.local_worker_pids()) == ["local-2"]
        logs = sorted(p.name for p in Path(agg._pool._log_dir).glob("local-*.log"))
        assert logs == ["local-0.log", "local-2.log"]  # no local worker was started (and refused) as local-1
    finally:
        agg.close()
        if remote is not None:
            stop_process(remote)


def test_launched_pool_restarts_workers_and_the_aggregator_follows(router, scene_root):
    launch, line = _start_cli("launch", "--workers", "1", "--run-id", "run-c", "--connect", router,
                              "--scene-root", str(scene_root), "--backend", "raycast", "--worker-prefix", "lw")
    assert "launch ready" in line
    try:
        with make_aggregator(pool={"connect": (router,), "num_local_workers": 0, "run_id": "run-c"},
                             scenes=SCENES) as agg:
            assert agg.workers == ["lw-0"]
            poses = spawn_poses(agg)
            before = agg.observe(poses)
            pid = agg.health()[0]["pid"]
            os.kill(pid, signal.SIGKILL)
            assert wait_for(lambda: [h.get("pid") for h in agg.health()] not in ([], [pid], [None]), timeout=60)
            obs = agg.observe(poses)  # same worker id, new process: scenes reloaded there, in the background
            assert obs.lost.all()
            np.testing.assert_array_equal(obs.images["depth"], before.images["depth"])
            assert wait_for(lambda: not agg.observe(poses).lost.any(), timeout=30)
            np.testing.assert_array_equal(agg.observe(poses).images["depth"], before.images["depth"])
            new_pid = agg.health()[0]["pid"]
    finally:
        assert stop_process(launch) == 0
    assert wait_for(lambda: not pid_alive(new_pid), timeout=10)


def test_a_router_outage_pauses_a_local_pool_and_nobody_is_killed():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router, line = _start_cli("router", "--listen", endpoint)
    assert "router ready" in line
    try:
        with make_aggregator(pool={"connect": (endpoint,), "num_local_workers": 2, "run_id": "outage",
                                   "step_timeout_s": 2.0, "outage_limit_s": 60.0}, scenes=SCENES) as agg:
            poses = spawn_poses(agg)
            before = agg.observe(poses)
            pids = dict(agg.local_worker_pids())
            assert stop_process(router) == 0  # the router is gone for about 6 s
            restarted = []
            timer = threading.Timer(6.0, lambda: restarted.append(_start_cli("router", "--listen", endpoint)[0]))
            timer.start()
            try:  # steps get lost data or wait for workers meanwhile, never an error
                assert wait_for(lambda: not agg.observe(poses).lost.any(), timeout=90)
            finally:
                timer.join()
                router = restarted[0] if restarted else router
            np.testing.assert_array_equal(agg.observe(poses).images["depth"], before.images["depth"])
            survivors = [w for w, pid in pids.items() if pid_alive(pid)]
            assert survivors, f"every local worker was killed during the outage: {pids}"
    finally:
        stop_process(router)


def test_an_outage_longer_than_the_limit_names_the_router():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router, _ = _start_cli("router", "--listen", endpoint)
    try:
        with make_aggregator(pool={"connect": (endpoint,), "num_local_workers": 1, "run_id": "outage2",
                                   "step_timeout_s": 1.0, "outage_limit_s": 3.0}, scenes=SCENES) as agg:
            poses = spawn_poses(agg)
            agg.observe(poses)
            assert stop_process(router) == 0
            with pytest.raises(NoWorkersError, match="no scene worker reachable for outage_limit_s=3 s"):
                for _ in range(20):
                    agg.observe(poses)
    finally:
        stop_process(router)


def test_launch_refuses_a_lease_its_workers_would_refuse(capsys):
    """Checked before any worker starts: each would exit on it and be restarted for ever."""
    from visfly_dist.cli import main

    assert main(["launch", "--workers", "1", "--run-id", "r", "--connect", "tcp/127.0.0.1:7447", "--lease-ms", "50"]) == 2
    captured = capsys.readouterr()
    assert "--lease-ms: lease_ms=50 must be in [200, 600000]" in captured.err and "ready" not in captured.out


def test_closing_unloads_the_run_s_scenes_from_remote_workers(router, scene_root):
    """A worker started by hand outlives the run: it is asked to drop the run's scenes at close,
    instead of holding them until the next run with the run id finds them."""
    from tests.helpers import call, client_session
    from visfly_dist.protocol.messages import Health

    remote = start_worker("run-unload", router, scene_root, connect=True, worker_id="remote-u")
    agg = make_aggregator(pool={"connect": (router,), "num_local_workers": 0, "run_id": "run-unload"}, scenes=SCENES)
    try:
        agg.start()
        held = {h["worker_id"]: h["scenes"] for h in agg.health()}
        assert len(held["remote-u"]) == 2  # both slots
        agg.close()
        with client_session(router) as session:
            ok, health = call(session, remote.rpc_key, Health().to_message())
        assert ok and health["scenes"] == [] and health["loading"] == []
    finally:
        agg.close()
        stop_process(remote)


def test_a_second_trainer_on_a_run_id_in_use_is_refused_until_the_first_closes(router, scene_root):
    """Two trainers on one run id would load their scenes under the same keys on the same workers."""
    from visfly_dist.errors import ConfigError

    pool = {"connect": (router,), "num_local_workers": 1, "run_id": "run-twice"}
    first = make_aggregator(pool=pool, scenes=SCENES)
    second = make_aggregator(pool=pool, scenes=SCENES)
    third = make_aggregator(pool=pool, scenes=SCENES)
    try:
        first.start()
        with pytest.raises(ConfigError, match="run id 'run-twice' is in use by another trainer"):
            second.start()
        assert first.workers == ["local-0"]  # the refused one started no worker of its own
        poses = spawn_poses(first)
        np.testing.assert_allclose(first.observe(poses).images["depth"], reference(first, poses)["depth"], atol=1e-4)
        first.close()
        third.start()  # the token went with the first trainer
        assert third.workers == ["local-0"]
    finally:
        for agg in (first, second, third):
            agg.close()
