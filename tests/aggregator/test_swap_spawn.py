"""Spawn sampling is deterministic for a seed; scenes swap after ``swap_every_resets`` resets."""

from __future__ import annotations

import numpy as np
import pytest

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


def test_swap_after_enough_resets(pair):
    agg = pair[0]
    before = [agg.slot_source(s) for s in range(2)]
    assert not agg.note_resets(np.array([0, 1])).any()       # slot 0: 2 resets
    assert not agg.note_resets(np.array([2])).any()          # slot 1: 1 reset
    mask = agg.note_resets(np.array([0, 3]))                 # slot 0: 3 -> swap; slot 1: 2
    assert mask.tolist() == [True, True, False, False]
    assert agg.slot_source(0) != before[0] and agg.slot_source(1) == before[1]
    mask = agg.note_resets(np.array([2]))                    # slot 1: 3 -> swap
    assert mask.tolist() == [False, False, True, True]
    assert agg.slot_source(1) not in before
    poses = np.zeros((4, 7))
    poses[:, :3] = _spawn(agg, [0, 1, 2, 3])                 # pools refetched from the new scenes
    poses[:, 3] = 1.0
    obs = agg.observe(poses)
    assert not obs.lost.any() and not obs.collision.any()

