"""A worker process's life: readiness, liveliness, signals, its parent, shared memory, and its CLI."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zenoh

from tests.helpers import REPO, call, client_session, free_port, start_worker, stop_process, wait_for
from visfly_dist.protocol import keys
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.messages import Health, LoadScene, ScenePoses, StepRequest
from visfly_dist.protocol.session import SessionConfig, open_session
from visfly_dist.protocol import shm

pytestmark = pytest.mark.worker

RUN = f"life{os.getpid()}"


class AliveWatch:
    """Liveliness events of one run's workers, as ``(kind, worker_id)`` pairs."""

    def __init__(self, session) -> None:
        self.events: list[tuple[str, str]] = []
        self._sub = session.liveliness().declare_subscriber(keys.workers_alive_pattern(RUN), self._on, history=True)

    def _on(self, sample) -> None:
        kind = "put" if sample.kind == zenoh.SampleKind.PUT else "delete"
        self.events.append((kind, keys.worker_id_from_alive_key(str(sample.key_expr))))

    def saw(self, kind: str, worker_id: str, timeout: float = 10.0) -> bool:
        return wait_for(lambda: (kind, worker_id) in self.events, timeout)

    def close(self) -> None:
        self._sub.undeclare()


def _open_zenoh_files(pid: int) -> set[str]:
    return shm._zenoh_files_open_in(Path(f"/proc/{pid}/fd"))


def _big_step(session, proc) -> None:
    """Load a scene and step 100 agents of 64x64 depth: a 1.6 MB reply, over shared memory if on."""
    ok, reply = call(session, proc.rpc_key, LoadScene("s0", "gen:pillars?seed=1", (CameraSpec(),)).to_message())
    assert ok, reply
    poses = np.tile(np.array([[2.0, 0.0, 1.5, 1.0, 0.0, 0.0, 0.0]], np.float32), (100, 1))
    ok, reply = call(session, proc.rpc_key, StepRequest((ScenePoses("s0", poses),)).to_message())
    assert ok and reply["images"]["depth"].shape == (100, 1, 64, 64)


def test_sigterm_withdraws_the_token_exits_0_and_leaves_no_orphaned_shared_memory(scene_root):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = start_worker(RUN, endpoint, scene_root)
    try:
        with client_session(endpoint) as session:
            watch = AliveWatch(session)
            assert watch.saw("put", proc.worker_id)
            _big_step(session, proc)
            held = _open_zenoh_files(proc.pid)
            assert held, "the worker should hold Zenoh shared-memory segments after a 1.6 MB reply"
            assert stop_process(proc) == 0, proc.stderr_text()
            assert watch.saw("delete", proc.worker_id)
            watch.close()
        # Every segment the worker held is gone, or still held by a live process (this one).
        assert not held & shm.orphaned_segments()
    finally:
        stop_process(proc)


def test_sigkill_is_seen_as_the_token_vanishing(scene_root):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = start_worker(RUN, endpoint, scene_root)
    held: set[str] = set()
    try:
        with client_session(endpoint) as session:
            watch = AliveWatch(session)
            assert watch.saw("put", proc.worker_id)
            held = _open_zenoh_files(proc.pid)
            proc.kill()
            proc.wait()
            assert watch.saw("delete", proc.worker_id)
            watch.close()
            replies = list(session.get(proc.rpc_key, payload=b"", timeout=2.0))
            assert replies == []  # a dead worker is silence, not an error
    finally:
        stop_process(proc)
        for path in held & shm.orphaned_segments():  # what the killed worker left: Zenoh's own rule
            os.unlink(path)


def test_worker_exits_when_its_parent_dies(scene_root):
    parent = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = start_worker(RUN, endpoint, scene_root, extra_args=["--parent-pid", str(parent.pid)])
    try:
        assert proc.poll() is None
        parent.kill()
        parent.wait()
        assert proc.wait(timeout=15) == 0, proc.stderr_text()
    finally:
        stop_process(proc)
        stop_process(parent)


def test_client_mode_worker_joins_a_listening_peer_and_loads_no_torch(scene_root):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_session(SessionConfig(mode="peer", listen=(endpoint,), shared_memory=False))
    proc = None
    try:
        proc = start_worker(RUN, endpoint, scene_root, shm=False, connect=True)
        assert wait_for(lambda: len(list(session.liveliness().get(proc.alive_key, timeout=1.0))) == 1)
        _big_step(session, proc)
        ok, health = call(session, proc.rpc_key, Health().to_message())
        assert ok and health["scenes"] == ["s0"]
        maps = Path(f"/proc/{proc.pid}/maps").read_text()
        assert "libtorch" not in maps, "the worker process must not import torch"
    finally:
        if proc is not None:
            stop_process(proc)
        session.close()


def _cli(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "visfly_dist.cli", "worker", "--run-id", RUN, *args],
                          capture_output=True, text=True, timeout=60, env=env, cwd=REPO)


@pytest.mark.parametrize("args, message", [
    (["--listen", "tcp/127.0.0.1:0", "--scene-root", "/no/such/dir"], "--scene-root \\['/no/such/dir'\\] are not existing"),
    (["--listen", "localhost:7447"], "endpoint 'localhost:7447' must look like tcp/HOST:PORT"),
    (["--connect", "tcp/127.0.0.1:99999"], "endpoint 'tcp/127.0.0.1:99999' must look like"),
    ([], "give --connect ENDPOINT .* or --listen ENDPOINT"),
    (["--mode", "client", "--listen", "tcp/127.0.0.1:0"], "needs --mode peer"),
    (["--listen", "tcp/127.0.0.1:0", "--backend", "vulkan"], "invalid choice: 'vulkan'"),
    (["--listen", "tcp/127.0.0.1:0", "--worker-id", "a/b"], "worker_id='a/b' must be"),
    (["--listen", "tcp/127.0.0.1:0", "--lease-ms", "5"], "lease_ms=5 must be in"),
    (["--connect", f"tcp/127.0.0.1:{free_port()}"], "could not open a Zenoh client session"),
])
def test_bad_arguments_exit_2_with_a_clear_error(args, message):
    out = _cli(*args)
    assert out.returncode == 2, out
    assert re.search(message, out.stderr), out.stderr
    assert "ready" not in out.stdout
