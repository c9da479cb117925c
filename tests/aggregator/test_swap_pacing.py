"""Swaps asked for faster than a worker loads: at most two loads wait on a worker, and a load that
times out on a worker that still answers backs off from that worker instead of orphaning its slots.
Real local workers."""

from __future__ import annotations

import time

import numpy as np

from tests.aggregator.conftest import make_aggregator, spawn_poses
from visfly_dist.aggregator.scene_moves import SWAP_LOADS_PER_WORKER

DENSE = "gen:garage-stones?density=0.9"  # about 1.3 s to generate on these machines


def _swapping(agg) -> list[int]:
    """Slots with a swap whose load has not been taken in yet (not armed, not waiting for pools)."""
    return [s.index for s in agg.table.slots if s.move is not None and s.incoming is None]


def test_due_swaps_wait_for_their_worker_and_each_slot_swaps_in_turn():
    agg = make_aggregator(pool={"num_local_workers": 1},
                          scenes={"sources": ("gen:pillars",), "num_scenes": 6, "agents_per_scene": 1,
                                  "swap_every_resets": 1})
    with agg:
        before = [agg.slot_source(s) for s in range(agg.num_scenes)]
        agg.note_resets(np.arange(agg.num_agents))  # every slot is due at once
        assert len(_swapping(agg)) == SWAP_LOADS_PER_WORKER == 2  # the other four wait: no queue on the worker
        poses = spawn_poses(agg)
        deadline = time.monotonic() + 60.0
        while any(agg.slot_source(s) == before[s] for s in range(agg.num_scenes)):
            assert time.monotonic() < deadline, [agg.slot_source(s) for s in range(agg.num_scenes)]
            assert not agg.observe(poses).lost.any()
            agg.take_next_scene()
            moved = agg.note_resets(np.arange(agg.num_agents))  # episodes end: armed swaps are taken over
            if len(moved):
                poses = spawn_poses(agg)
        assert agg.assignment() == {s: "local-0" for s in range(agg.num_scenes)}


def test_a_swap_load_that_times_out_on_a_live_worker_backs_off_and_the_worker_keeps_its_slots():
    agg = make_aggregator(pool={"num_local_workers": 1},
                          scenes={"sources": (DENSE,), "num_scenes": 2, "agents_per_scene": 1, "swap_every_resets": 1})
    with agg:
        pids, sources = agg.local_worker_pids(), [agg.slot_source(s) for s in range(2)]
        agg.pool_config.startup_timeout_s = 0.2  # the deadline of loads: this garage takes several times that
        agg.note_resets(np.array([0]))
        assert _swapping(agg) == [0]
        poses = spawn_poses(agg)
        deadline = time.monotonic() + 30.0
        while _swapping(agg):
            assert time.monotonic() < deadline
            assert not agg.observe(poses).lost.any()
        agg.note_resets(np.array([1]))                                      # within the back-off's first second
        assert _swapping(agg) == []                                         # it backs off: no new load now
        assert agg.table.slots[0].incoming is None and agg.table.slots[0].move is None  # the swap was given up
        assert [agg.slot_source(s) for s in range(2)] == sources
        assert agg.assignment() == {0: "local-0", 1: "local-0"}            # nothing was orphaned
        assert agg.local_worker_pids() == pids                              # nor the worker replaced
        for _ in range(5):
            assert not agg.observe(poses).lost.any()
