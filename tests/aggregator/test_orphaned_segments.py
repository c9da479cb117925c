"""A learner killed with a request in flight leaves nothing behind: its segments are memfds, never
files in /dev/shm, and go with the last process that holds one. A worker that still holds the
killed learner's segment keeps writing (no SIGBUS), and a worker asked for it afterwards gets no
segment (the images go inline)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from tests.helpers import REPO
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.codec import decode, encode
from visfly_dist.protocol.image_segment import NAME_PREFIX, SegmentTarget
from visfly_dist.scene_worker.image_segments import SegmentMappings

CAMS = (CameraSpec(name="depth", kind="depth", width=32, height=24),)

# A learner that takes a segment for a request to a worker (as Aggregator.submit does), prints the
# request's target and waits for a worker answer that never comes.
LEARNER = r"""
import sys
from visfly_dist.aggregator.image_shm import ImageSegments
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.codec import encode

segments = ImageSegments(sys.argv[1], (CameraSpec(name="depth", kind="depth", width=32, height=24),))
step = segments.offer([("local-0", 1)], 12, 0)
target = segments.target(step, ("local-0", 1), [0], [])
sys.stdout.buffer.write(encode({"type": "target", "target": target.to_message()}).hex().encode() + b"\n")
sys.stdout.flush()
sys.stdin.read()
"""


@pytest.fixture
def learner():
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    proc = subprocess.Popen([sys.executable, "-c", LEARNER, "orphan"], cwd=REPO, env=env, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE)
    line = proc.stdout.readline()
    assert line, proc.poll()
    yield proc, SegmentTarget.parse(decode(bytes.fromhex(line.decode()))["target"])
    proc.kill()
    proc.wait(timeout=10)


def test_a_killed_learner_leaves_no_file_and_its_workers_survive(learner):
    proc, target = learner
    assert target.pid == proc.pid and not [n for n in os.listdir("/dev/shm") if n.startswith(NAME_PREFIX)]
    assert os.readlink(target.path()) == f"/memfd:{target.name} (deleted)"
    images = {"depth": np.full((12, *CAMS[0].shape), 3.0, np.float32)}
    starts, counts = np.array([0]), np.array([12])
    worker = SegmentMappings()
    views, why = worker.views(target, CAMS, 12)
    assert why == "" and views is not None
    assert worker.publish(target, images, starts, counts) == ""
    proc.send_signal(signal.SIGKILL)  # with its request unanswered
    proc.wait(timeout=10)
    assert not [n for n in os.listdir("/dev/shm") if n.startswith(NAME_PREFIX)]
    # The worker that holds the segment writes on (into memory that goes with its descriptor) ...
    assert worker.views(target, CAMS, 12)[1] == "" and worker.publish(target, images, starts, counts) == ""
    worker.close()
    # ... and one asked for it now finds nothing to open: it replies inline.
    late = SegmentMappings()
    views, why = late.views(target, CAMS, 12)
    assert views is None and "cannot open image segment" in why
    late.close()
