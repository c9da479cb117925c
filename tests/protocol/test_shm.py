"""Shared-memory hygiene of a client (training) process, as a real subprocess talking to a real worker:
after its session is closed and :func:`release_segments` runs, and after it exits, no Zenoh segment
file of its own is left in /dev/shm."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import REPO, stop_process
from visfly_dist.protocol import shm

pytestmark = pytest.mark.worker

CLIENT = r"""
import json, sys
from pathlib import Path
import numpy as np
from tests.helpers import call
from visfly_dist.protocol import shm
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.messages import LoadScene, ScenePoses, StepRequest
from visfly_dist.protocol.session import client_of, open_session

endpoint, rpc_key = sys.argv[1], sys.argv[2]
session = open_session(client_of([endpoint], shared_memory=True))
other = open_session(client_of([endpoint], shared_memory=True))
assert call(session, rpc_key, LoadScene("s0", "gen:empty", (CameraSpec(),)).to_message())[0]
poses = np.tile(np.array([[0.0, 0.0, 1.5, 1.0, 0.0, 0.0, 0.0]], np.float32), (200, 1))  # 5.6 kB out, 3.3 MB back
for _ in range(3):
    assert call(session, rpc_key, StepRequest((ScenePoses("s0", poses),)).to_message())[0]
held = sorted(shm._zenoh_files_open_in(Path("/proc/self/fd")))
session.close()
early = shm.release_segments()          # `other` is still open: nothing may go
other.close()
removed = shm.release_segments()
print(json.dumps({"held": held, "early": early, "removed": removed}), flush=True)
sys.stdin.readline()
"""


def files_held_by_processes_other_than(pid: int) -> set[str]:
    """Zenoh segment files open in any process but ``pid``."""
    held: set[str] = set()
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit() and int(proc.name) != pid:
            held |= shm._zenoh_files_open_in(proc / "fd")
    return held


def test_a_client_leaves_no_segment_behind_after_close_and_exit(worker_factory):
    worker = worker_factory(f"shm{os.getpid()}", shm=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    client = subprocess.Popen([sys.executable, "-c", CLIENT, worker.endpoint, worker.rpc_key], cwd=REPO, env=env,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        report = json.loads(client.stdout.readline() or "{}")
        assert report, client.stderr.read() if client.poll() is not None else "no report"
        held = set(report["held"])
        # the client's own files: those no other process holds (the worker's, or a process of an
        # earlier test still exiting, are not the client's to remove)
        others = files_held_by_processes_other_than(client.pid)
        own = held - others
        assert own, f"the client should have made segments of its own: held {held}, others {others}"
        assert report["early"] == [], "segments were released while a session was still open"
        # Closed and released, still running: its own files are gone already.
        assert set(report["removed"]) == own and not any(Path(p).exists() for p in own)
        client.stdin.write("exit\n")
        client.stdin.flush()
        assert client.wait(timeout=30) == 0, client.stderr.read()
        # Exited: what it held of the worker's is the worker's to remove; nothing is orphaned.
        assert not held & shm.orphaned_segments()
        assert stop_process(worker) == 0
        assert not held & shm.orphaned_segments() and not any(Path(p).exists() for p in held)
    finally:
        if client.poll() is None:
            client.kill()
        client.wait()
        for pipe in (client.stdin, client.stdout, client.stderr):
            pipe.close()
