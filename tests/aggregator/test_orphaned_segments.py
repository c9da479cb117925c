"""Image segment files left in /dev/shm by a learner killed with a request in flight are removed by
the next learner on the host; files another live process holds open or maps are kept."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from tests.aggregator.conftest import make_aggregator
from tests.helpers import REPO
from visfly_dist.protocol.image_segment import NAME_PREFIX, SHM_DIR

# A learner that takes a segment for a request to a worker (as Aggregator.submit does), prints the
# file's path and waits for a worker answer that never comes.
LEARNER = r"""
import sys
from visfly_dist.aggregator.image_shm import ImageSegments
from visfly_dist.protocol.cameras import CameraSpec

segments = ImageSegments(sys.argv[1], (CameraSpec(name="depth", kind="depth", width=32, height=24),))
step = segments.offer([("local-0", 1)], 12, 0)
print(step.segment.path, flush=True)
sys.stdin.read()
"""


def _learner(run: str) -> tuple[subprocess.Popen, str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    proc = subprocess.Popen([sys.executable, "-c", LEARNER, run], cwd=REPO, env=env, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    path = proc.stdout.readline().strip()
    assert path.startswith(f"{SHM_DIR}/{NAME_PREFIX}{run}-") and os.path.exists(path), (path, proc.poll())
    return proc, path


@pytest.fixture
def learners():
    procs: list[subprocess.Popen] = []
    yield procs
    for proc in procs:
        proc.kill()
        proc.wait(timeout=10)


def test_a_new_learner_removes_orphaned_segments_and_keeps_those_in_use(learners):
    killed, orphan = _learner("orphan-killed")
    alive, in_use = _learner("orphan-alive")
    learners += [killed, alive]
    killed.send_signal(signal.SIGKILL)  # with its request unanswered: the file stays behind
    killed.wait(timeout=10)
    assert os.path.exists(orphan)
    held_open = os.path.join(SHM_DIR, f"{NAME_PREFIX}orphan-held-0000")  # open here, not mapped
    with open(held_open, "wb") as held:
        held.write(b"\0" * 64)
        held.flush()
        try:
            agg = make_aggregator(pool={"shared_memory": True})  # builds its image segments: no worker yet
            agg.close()
            assert not os.path.exists(orphan)
            assert os.path.exists(in_use), "a live learner's segment was removed"
            assert os.path.exists(held_open), "a segment file held open by a live process was removed"
        finally:
            os.unlink(held_open)
    alive.send_signal(signal.SIGTERM)
    alive.wait(timeout=10)
    make_aggregator(pool={"shared_memory": True}).close()  # a learner that ended by a signal, too
    assert not os.path.exists(in_use)
