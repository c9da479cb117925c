"""Spawn draws are pure functions of each agent's seed and draw count, and spawn specs do not
depend on how a task spells its corners (pure, no workers)."""

from __future__ import annotations

import numpy as np
import pytest

from visfly_dist.aggregator.spawn_pools import AgentStreams, counter_draws, spawn_spec
from visfly_dist.errors import ConfigError


def test_each_draw_is_counter_draws_of_the_agents_seed_and_count():
    streams = AgentStreams(12)
    streams.reseed(np.arange(12), 7)
    streams.reseed(np.array([3, 9]), [2**62, -5])
    seeds = (7 + np.arange(12)).astype(np.uint64)
    seeds[3], seeds[9] = np.uint64(2**62), np.int64(-5).astype(np.uint64)
    count = np.zeros(12, np.uint64)
    rng = np.random.default_rng(0)
    for i in range(300):
        k = int(rng.integers(0, 6))
        agents = np.sort(rng.choice(12, k, replace=False)) if i % 2 else rng.integers(0, 12, k)  # unique, or repeats
        expected = []
        for a in agents.tolist():
            expected.append(counter_draws(seeds[a:a + 1], count[a:a + 1])[0])
            count[a] += np.uint64(1)
        assert streams.draw(agents).tolist() == [int(v) for v in expected]


@pytest.mark.parametrize("a, b", [((1, -2.5, 0), (3.0, 2, 0.5)), ([1, -2.5, 0], np.array([3.0, 2, 0.5])),
                                  (tuple(np.array([1.0, -2.5, 0.0])), (np.float32(3), np.int64(2), 0.5)),
                                  (np.array([[1, -2.5, 0]]), [3, 2, 0.5])])
def test_a_spec_is_the_same_however_its_corners_are_spelled(a, b):
    spec = spawn_spec("uniform", a, b, 0.5)
    assert spec == ("uniform", (1.0, -2.5, 0.0), (3.0, 2.0, 0.5), 0.5)
    assert all(type(v) is float for v in (*spec.a, *spec.b, spec.clearance))


@pytest.mark.parametrize("args", [("uniform", (1, 0, 0), (0, 1, 1), 0.5), ("normal", (0, 0, 0), (1, -1, 1), 0.5),
                                  ("uniform", (0, 0, float("nan")), (1, 1, 1), 0.5), ("box", (0, 0, 0), (1, 1, 1), 0.5),
                                  ("uniform", (0, 0), (1, 1, 1), 0.5), ("uniform", (0, 0, 0), (1, 1, 1), 101)])
def test_an_invalid_spec_is_refused(args):
    with pytest.raises(ConfigError):
        spawn_spec(*args)
