"""Worker failures: a killed or hung worker costs one call's data for its agents, never a hang."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest

from tests.aggregator.conftest import make_aggregator, pid_alive, spawn_poses
from tests.helpers import wait_for
from visfly_dist.errors import NoWorkersError


def _victim(agg):
    worker = agg.workers[0]
    slots = [s for s, w in agg.assignment().items() if w == worker]
    return worker, agg.local_worker_pids()[worker], np.isin(agg.agent_scene, slots)


def test_sigkill_moves_scenes_then_no_workers_left():
    with make_aggregator(pool={"respawn": False}) as agg:
        poses = spawn_poses(agg)
        before = agg.observe(poses)
        victim, pid, affected = _victim(agg)
        os.kill(pid, signal.SIGKILL)

        obs = agg.observe(poses)
        assert obs.lost.tolist() == affected.tolist()
        np.testing.assert_array_equal(obs.images["depth"], before.images["depth"])  # fresh or last good: same poses
        survivor = [w for w in agg.workers]
        assert len(survivor) == 1 and victim not in survivor
        assert set(agg.assignment().values()) == set(survivor)

        again = agg.observe(poses)
        assert not again.lost.any()
        np.testing.assert_array_equal(again.images["depth"], before.images["depth"])
        np.testing.assert_array_equal(again.distance, before.distance)

        os.kill(agg.local_worker_pids()[survivor[0]], signal.SIGKILL)
        with pytest.raises(NoWorkersError, match="no live scene worker left"):
            agg.observe(poses)


def test_hung_worker_is_killed_replaced_and_rebalanced():
    # A long lease keeps the hung worker's token alive: only the step deadline can catch it.
    with make_aggregator(pool={"respawn": True, "step_timeout_s": 2.0, "lease_ms": 10_000}) as agg:
        poses = spawn_poses(agg)
        before = agg.observe(poses)
        victim, pid, affected = _victim(agg)
        os.kill(pid, signal.SIGSTOP)  # a hang: the process lives but answers nothing

        obs = agg.observe(poses)  # waits out the deadline, then serves the last good data
        assert obs.lost.tolist() == affected.tolist()
        assert obs.timings["total_s"] >= 2.0
        np.testing.assert_array_equal(obs.images["depth"], before.images["depth"])
        assert wait_for(lambda: not pid_alive(pid), timeout=10)  # the hung worker was killed
        assert wait_for(lambda: len(agg.workers) == 2, timeout=60), agg.workers
        assert victim not in agg.workers

        again = agg.observe(poses)  # the replacement gets its share of the scenes back
        assert not again.lost.any()
        np.testing.assert_array_equal(again.images["depth"], before.images["depth"])
        per_worker = sorted(list(agg.assignment().values()).count(w) for w in agg.workers)
        assert per_worker == [2, 2]
