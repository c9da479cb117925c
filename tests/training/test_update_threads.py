"""The timed choice of PPO's update threads (pure logic, fake timings)."""

from __future__ import annotations

import pytest

from visfly_dist.errors import ConfigError
from visfly_dist.training.threads import UpdateThreadChooser


def run(chooser: UpdateThreadChooser, seconds_of: dict[int, float], updates: int) -> list[int]:
    used = []
    for _ in range(updates):
        threads = chooser.next()
        chooser.record(threads, seconds_of[threads])
        used.append(threads)
    return used


def test_starts_with_the_preferred_count_then_times_the_other_less_and_less():
    chooser = UpdateThreadChooser([2, 1], reprobe_every=4)
    used = run(chooser, {2: 8.0, 1: 14.0}, 40)      # a quiet machine: 2 threads win
    assert used[:5] == [2, 2, 2, 2, 1]                # the other count is first timed after 4 updates
    retimings = [i for i, t in enumerate(used) if t == 1][1:]
    assert retimings == [13, 30]                      # gaps of 8 then 16: each timing confirmed the choice
    assert chooser.best == 2


def test_switches_at_the_first_timing_when_the_preferred_count_is_slow():
    chooser = UpdateThreadChooser([2, 1], reprobe_every=4)
    used = run(chooser, {2: 77.0, 1: 20.0}, 12)      # a loaded machine from the start
    assert used[:5] == [2, 2, 2, 2, 1] and set(used[5:9]) == {1}
    assert chooser.best == 1


def test_follows_the_machine_when_outside_load_makes_more_threads_slower():
    chooser = UpdateThreadChooser([2, 1], reprobe_every=4)
    run(chooser, {2: 8.0, 1: 14.0}, 6)
    used = run(chooser, {2: 77.0, 1: 20.0}, 20)      # other work arrives
    assert used[0] == 2 and set(used[1:7]) == {1}     # one slow update with 2 threads, then one thread
    assert used.count(2) <= 3 and chooser.best == 1


def test_a_fixed_count_is_always_used():
    chooser = UpdateThreadChooser([3])
    assert run(chooser, {3: 1.0}, 10) == [3] * 10


def test_bad_candidates_are_refused():
    with pytest.raises(ConfigError):
        UpdateThreadChooser([])
    with pytest.raises(ConfigError):
        UpdateThreadChooser([0, 1])
    with pytest.raises(ConfigError):
        UpdateThreadChooser([2, 1], reprobe_every=1)
