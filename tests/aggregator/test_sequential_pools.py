"""Several envs made one after another in one process (a hyperparameter sweep, ``bench step --rows``).

Regression: closing the first pool unlinked this process's Zenoh shared-memory files, including
the metadata segments Zenoh keeps per process (not per session) and reuses in every later session.
A worker of the second pool could then not map any shared-memory buffer the learner sent (a
request over Zenoh's shared-memory threshold, e.g. a step of 100 agents): Zenoh dropped the query
without a word and every step ended in ``Timeout``, worker after worker. Runs in a fresh
subprocess, so that the first pool is the first to allocate shared memory in that process.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tests.helpers import REPO

pytestmark = pytest.mark.worker

SCRIPT = r"""
import numpy as np
from visfly_dist.aggregator.config import PoolConfig
from visfly_dist.aggregator.pool import WorkerPool
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.messages import LoadScene, ScenePoses, StepRequest

STEPS = 20
camera = CameraSpec(name="depth", kind="depth", width=8, height=8)
poses = np.tile(np.array([[0.0, 0.0, 1.5, 1.0, 0.0, 0.0, 0.0]], np.float32), (200, 1))  # 5.6 kB: shared memory
for n in range(2):
    pool = WorkerPool(PoolConfig(num_local_workers=1, backend="raycast", shared_memory=True, lease_ms=1000), f"seq{n}")
    pool.open()
    try:
        (wid,) = pool.wait_for(1, 60.0)
        (reply,) = pool.call([(wid, LoadScene("s0", "gen:empty", (camera,)).to_message())], timeout_s=30.0)
        assert reply.message is not None, f"pool {n}: load_scene: {reply.failure or reply.error}"
        for i in range(STEPS):  # the first few may use segments of this session only
            (reply,) = pool.call([(wid, StepRequest((ScenePoses("s0", poses),)).to_message())], timeout_s=3.0)
            assert reply.message is not None, f"pool {n}, step {i}: {reply.failure or reply.error}"
        print(f"pool {n} ok", flush=True)
    finally:
        pool.close()
"""


def test_a_second_pool_in_the_same_process_gets_its_large_requests_answered():
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    done = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0 and done.stdout.split("\n")[:2] == ["pool 0 ok", "pool 1 ok"], (
        f"exit {done.returncode}\nstdout: {done.stdout}\nstderr: {done.stderr[-3000:]}")
