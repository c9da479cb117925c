"""Spawn sampling is deterministic for a seed; scenes swap after ``swap_every_resets`` resets, each\nagent moving into the new scene at its own episode end."""

from __future__ import annotations

import time

import numpy as np
import pytest

from tests.helpers import wait_for

from tests.aggregator.conftest import make_aggregator

SCENES = {"sources": ("gen:garage-stones",), "num_scenes": 2, "agents_per_scene": 2, "swap_every_resets": 3}


@pytest.fixture(scope="module")
def pair():
    a = make_aggregator(pool={"num_local_workers": 1}, scenes=SCENES, seed=5)
    b = make_aggregator(pool={"num_local_workers": 1}, scenes=SCENES, seed=5)
    try:
        yield a.start(), b.start()
    finally:
        a.close()
        b.close()


def _spawn(agg, agents):
    return agg.sample_spawn(np.asarray(agents), "normal", (9.0, 0.0, 2.0), (3.0, 2.0, 0.5), 0.4)


def test_same_seed_same_spawns(pair):
    a, b = pair
    assert [a.slot_source(s) for s in range(2)] == [b.slot_source(s) for s in range(2)]
    first = _spawn(a, [0, 1, 2, 3, 0])
    np.testing.assert_array_equal(first, _spawn(b, [0, 1, 2, 3, 0]))
    assert len({tuple(p) for p in first[:4]}) == 4  # distinct draws
    assert not np.array_equal(_spawn(a, [0, 1, 2, 3]), first[:4])  # the generator moves on


def _step_until_armed(agg, poses, timeout=60.0):
    """Steps go on while the next scene loads; ``take_next_scene`` reports its agents once it is ready."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        obs = agg.observe(poses)
        armed = agg.take_next_scene()
        if armed.any():
            return obs, armed
        time.sleep(0.05)
    raise AssertionError("no scene swap within the timeout")


def test_a_swap_loads_in_the_background_and_takes_over_at_each_agents_episode_end(pair):
    agg = pair[0]
    before = [agg.slot_source(s) for s in range(2)]
    poses = np.zeros((4, 7))
    poses[:, :3] = _spawn(agg, [0, 1, 2, 3])
    poses[:, 3] = 1.0
    agg.note_resets(np.array([0, 1]))                         # slot 0: 2 resets
    agg.note_resets(np.array([2]))                            # slot 1: 1 reset
    assert not agg.observe(poses).lost.any() and not agg.take_next_scene().any()
    agg.note_resets(np.array([0, 3]))                         # slot 0: 3 -> swap; slot 1: 2
    obs, armed = _step_until_armed(agg, poses)
    assert not obs.lost.any()
    assert armed.tolist() == [True, True, False, False]       # their next starts belong in the new scene
    assert agg.agent_sources() == [before[0]] * 2 + [before[1]] * 2  # nobody's running episode moved
    new = agg.table.slots[0].incoming.move.source
    assert new != before[0]
    next_starts = _spawn(agg, [0, 1])                         # drawn from the new scene's pool
    assert agg.note_resets(np.array([0])).tolist() == [0]     # agent 0's episode ends: it moves
    assert agg.agent_sources() == [new, before[0], before[1], before[1]] and agg.slot_source(0) == before[0]
    poses[0, :3] = next_starts[0]
    obs = agg.observe(poses)                                  # one slot, two scenes, one request
    assert not obs.lost.any() and not obs.collision[0]
    assert agg.note_resets(np.array([1])).tolist() == [1]     # the last one: slot 0 switches
    assert agg.slot_source(0) == new and agg.agent_sources()[:2] == [new, new]
    assert not agg.take_switched().any()                      # no running episode changed scene
    agg.note_resets(np.array([2]))                            # slot 1: 3 -> swap
    _, armed = _step_until_armed(agg, poses)
    assert armed.tolist() == [False, False, True, True]
    agg.note_resets(np.array([2, 3]))                         # both end together: switched at once
    assert agg.slot_source(1) not in before
    poses[:, :3] = _spawn(agg, [0, 1, 2, 3])                  # pools of the new scenes were fetched before the switch
    obs = agg.observe(poses)
    assert not obs.lost.any() and not obs.collision.any()
    assert wait_for(lambda: (agg.observe(poses), not agg.background_busy())[1], timeout=30)
    health = {h["worker_id"]: h["scenes"] for h in agg.health()}
    assert sorted(k for keys in health.values() for k in keys) == sorted(s.key for s in agg.table.slots)  # old keys unloaded


def test_spawn_pools_are_refreshed_and_stay_deterministic():
    draws = []
    for _ in range(2):
        with make_aggregator(pool={"num_local_workers": 1}, scenes=SCENES, seed=9) as agg:
            draws.append(np.concatenate([_spawn(agg, [0] * 64) for _ in range(12)]))  # 768 from a 256-point pool
    draws_a, draws_b = draws
    np.testing.assert_array_equal(draws_a, draws_b)  # refreshes swap in at a draw count, not a time
    first, last = {tuple(p) for p in draws_a[:256]}, {tuple(p) for p in draws_a[-128:]}
    assert len(last - first) > 64  # later draws come from fresh samples
