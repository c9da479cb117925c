"""LostHolds: an agent whose worker failed is held up to the bound, then cut once, then held again."""

import numpy as np

from visfly_dist.client.lost_holds import LostHolds

EVERYONE = np.ones(3, dtype=bool)


def test_a_lost_agent_is_held_until_the_bound_then_cut_once_then_held_again():
    holds = LostHolds(3, limit_s=2.0)
    lost = np.array([True, False, False])
    assert holds.update(EVERYONE, lost, now=10.0).tolist() == [True, False, False]   # first lost step
    assert holds.update(EVERYONE, lost, now=11.9).tolist() == [True, False, False]   # still within the bound
    assert holds.update(EVERYONE, lost, now=12.0).tolist() == [False, False, False]  # the bound: cut (once)
    assert holds.update(EVERYONE, lost, now=12.1).tolist() == [True, False, False]   # its next episode waits again


def test_a_served_step_ends_the_hold_and_other_groups_keep_theirs():
    holds = LostHolds(3, limit_s=2.0)
    holds.update(EVERYONE, np.array([True, True, False]), now=0.0)
    group = np.array([True, False, False])   # only agent 0 was stepped, and served
    assert not holds.update(group, np.zeros(3, dtype=bool), now=1.0).any()
    # agent 0 starts a new hold; agent 1, not stepped meanwhile, keeps the one from t=0
    assert holds.update(EVERYONE, np.array([True, True, False]), now=2.5).tolist() == [True, False, False]
    holds.served(np.array([0]))
    assert holds.update(EVERYONE, np.array([True, False, False]), now=4.0).tolist() == [True, False, False]


def test_no_bound_cuts_at_once():
    holds = LostHolds(2, limit_s=0.0)
    assert not holds.update(np.ones(2, dtype=bool), np.array([True, True]), now=5.0).any()
