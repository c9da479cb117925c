"""Worker failures: a killed or hung worker costs one call's data for its agents, never a hang."""

from __future__ import annotations

import logging
import os
import signal
import time

import numpy as np
import pytest

from tests.aggregator.conftest import make_aggregator, pid_alive, spawn_poses
from tests.helpers import wait_for
from visfly_dist.errors import NoWorkersError


def _victim(agg):
    worker = agg.workers[0]
    slots = [s for s, w in agg.assignment().items() if w == worker]
    return worker, agg.local_worker_pids()[worker], np.isin(agg.agent_scene, slots)


def _exited(pid: int) -> bool:
    """The process ended (gone, or a zombie its parent, this process, has not reaped yet)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


def _observe_until(agg, poses, condition, timeout=60.0):
    """Step until ``condition(obs)`` holds (scenes move in the background, between steps)."""
    deadline = time.monotonic() + timeout
    while True:
        obs = agg.observe(poses)
        if condition(obs) or time.monotonic() > deadline:
            return obs
        time.sleep(0.05)


def test_sigkill_moves_scenes_in_the_background_then_no_workers_left():
    with make_aggregator(pool={"respawn": False, "outage_limit_s": 2.0}) as agg:
        poses = spawn_poses(agg)
        before = agg.observe(poses)
        victim, pid, affected = _victim(agg)
        os.kill(pid, signal.SIGKILL)

        obs = agg.observe(poses)  # exactly the victim's agents lose this step; they keep their last good data
        assert obs.lost.tolist() == affected.tolist()
        np.testing.assert_array_equal(obs.images["depth"], before.images["depth"])
        survivor = [w for w in agg.workers]
        assert len(survivor) == 1 and victim not in survivor

        again = _observe_until(agg, poses, lambda o: not o.lost.any())  # re-placed without blocking a step
        assert not again.lost.any() and set(agg.assignment().values()) == set(survivor)
        np.testing.assert_array_equal(again.images["depth"], before.images["depth"])
        np.testing.assert_array_equal(again.distance, before.distance)

        os.kill(agg.local_worker_pids()[survivor[0]], signal.SIGKILL)
        served = []  # steps that returned after the last worker died
        with pytest.raises(NoWorkersError, match="no scene worker reachable for outage_limit_s=2"):
            for _ in range(3):
                served.append(agg.observe(poses))
        # the step that lost the last worker serves stale data, every agent marked lost; the next one waits
        # out the outage limit and raises: no step is taken as if data had come
        assert len(served) <= 1 and all(o.lost.all() for o in served), [o.lost.tolist() for o in served]


def test_a_dead_worker_s_log_is_named_when_it_is_replaced_and_kept_after_the_run(tmp_path, caplog):
    logs = tmp_path / "run" / "workers"  # made by the pool, as a training run's folder is
    with make_aggregator(pool={"log_dir": str(logs)}) as agg:
        poses = spawn_poses(agg)
        agg.observe(poses)
        victim, pid, _ = _victim(agg)
        os.kill(pid, signal.SIGKILL)
        assert wait_for(lambda: _exited(pid), timeout=10.0)
        with caplog.at_level(logging.WARNING, logger="visfly_dist.aggregator.pool"):
            # dropped when its request gets no reply, or replaced once its liveliness token is gone
            told = lambda: [r.getMessage() for r in caplog.records if "it exited" in r.getMessage()]  # noqa: E731
            assert wait_for(lambda: agg.observe(poses) is not None and told(), timeout=30.0), caplog.text
        message = told()[0]
        assert f"{victim}" in message and f"it exited (-9); the end of its log {logs / f'{victim}.log'}" in message
        assert "INFO loaded scene" in message  # the end of its log, quoted
    kept = sorted(p.name for p in logs.iterdir())
    assert f"{victim}.log" in kept and len(kept) == 3, kept  # both first workers' and the replacement's


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
        assert wait_for(lambda: not pid_alive(pid), timeout=10)  # the hung worker was killed (others answer)
        assert wait_for(lambda: len(agg.workers) == 2, timeout=60), agg.workers
        assert victim not in agg.workers

        def balanced(o):
            return not o.lost.any() and sorted(list(agg.assignment().values()).count(w) for w in agg.workers) == [2, 2]

        again = _observe_until(agg, poses, balanced)  # the replacement gets its share back, in the background
        assert balanced(again), agg.assignment()
        np.testing.assert_array_equal(again.images["depth"], before.images["depth"])


def test_every_local_worker_hung_at_once_is_replaced_and_the_run_goes_on():
    # Local workers on their private channels: no router or network between them and the run, so a
    # worker that answers neither its step nor a probe is hung itself, even when no other answers.
    with make_aggregator(pool={"respawn": True, "step_timeout_s": 2.0, "lease_ms": 10_000}) as agg:
        poses = spawn_poses(agg)
        before = agg.observe(poses)
        pids = list(agg.local_worker_pids().values())
        for pid in pids:
            os.kill(pid, signal.SIGSTOP)
        assert agg.observe(poses).lost.all()  # waits out the deadline, then serves the last good data
        assert wait_for(lambda: not any(pid_alive(p) for p in pids), timeout=10)  # both killed, not waited for
        again = _observe_until(agg, poses, lambda o: not o.lost.any())  # served by the first replacement up
        assert not again.lost.any() and not set(agg.local_worker_pids().values()) & set(pids)
        assert wait_for(lambda: len(agg.workers) == 2, timeout=60), agg.workers  # and both came up
        np.testing.assert_array_equal(again.images["depth"], before.images["depth"])


def test_an_unload_lost_on_the_way_is_retried_and_a_delivered_one_is_not():
    """A worker that rejoins is asked to unload scenes it no longer serves. When that request gets no
    reply (the link flapped again), the key goes back on the worker's list for the next attempt;
    when it is answered, it does not."""
    with make_aggregator(pool={"num_local_workers": 1}, scenes={"num_scenes": 1, "agents_per_scene": 1}) as agg:
        worker = agg.workers[0]
        served = agg.table.slots[0].key
        agg._send_unloads([("ghost", "old-key"), (worker, "never-loaded")])
        wait_for(lambda: (agg._apply_background(), not agg.background_busy())[1], 20)
        assert agg._moves.stale == {"ghost": {"old-key"}}  # no such worker: no reply, kept for a retry
        held = {h["worker_id"]: h.get("scenes") for h in agg.health()}
        assert held == {worker: [served]}  # the answered unload (unknown scene) changed nothing
