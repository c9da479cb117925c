"""The slot table alone: placement, orphaning, rebalancing and swaps as plans, against a fake pool."""

from __future__ import annotations

import numpy as np

from visfly_dist.aggregator.slots import SlotTable


class FakePool:
    """Which workers are live and their generations, as the real pool would report them."""

    def __init__(self, *workers: str) -> None:
        self.generations = {w: 1 for w in workers}

    @property
    def live(self) -> list[str]:
        return sorted(self.generations)

    def kill(self, worker: str) -> None:
        del self.generations[worker]

    def join(self, worker: str) -> None:
        self.generations[worker] = self.generations.get(worker, 0) + 1


def _carry_out(table: SlotTable, plan) -> None:
    """Every load answers: switch each planned slot."""
    for slot, move in plan:
        table.finish_move(slot, move, np.zeros((2, 3)), {})


def _counts(table: SlotTable, live) -> dict[str, int]:
    return {w: sum(s.worker == w for s in table.slots) for w in live}


def test_placement_spreads_orphans_over_the_least_loaded_workers():
    pool = FakePool("a", "b", "c")
    table = SlotTable([f"gen:x?seed={i}" for i in range(7)], agents_per_scene=2)
    plan = table.plan_placement(pool.live, pool.generations)
    assert len(plan) == 7 and all(table.slots[s].move is m for s, m in plan)
    assert table.plan_placement(pool.live, pool.generations) == []  # moves in flight are not planned twice
    _carry_out(table, plan)
    assert sorted(_counts(table, pool.live).values()) == [2, 2, 3]
    assert table.agents_of(3).tolist() == [6, 7] and table.agent_scene.tolist()[6:8] == [3, 3]


def test_a_dead_worker_orphans_exactly_its_slots_and_cancels_moves_towards_it():
    pool = FakePool("a", "b")
    table = SlotTable(["s"] * 4, agents_per_scene=1)
    _carry_out(table, table.plan_placement(pool.live, pool.generations))
    held_by_a = [s.index for s in table.slots if s.worker == "a"]
    pool.kill("a")
    assert table.orphan_worker("a") == held_by_a
    plan = table.plan_placement(pool.live, pool.generations)
    assert [s for s, _ in plan] == held_by_a and all(m.worker == "b" for _, m in plan)
    assert table.orphan_worker("b") == [s.index for s in table.slots if s.index not in held_by_a]
    assert all(s.move is None for s in table.slots)  # the loads towards b were cancelled
    assert table.plan_placement([], {}) == []


def test_rebalancing_moves_scenes_to_a_new_worker_until_loads_differ_by_at_most_one():
    pool = FakePool("a")
    table = SlotTable(["s"] * 6, agents_per_scene=1)
    _carry_out(table, table.plan_placement(pool.live, pool.generations))
    pool.join("b")
    plan = table.plan_rebalance(pool.live, pool.generations)
    assert len(plan) == 3 and all(m.worker == "b" and m.reason == "rebalance" for _, m in plan)
    assert all(table.slots[s].worker == "a" for s, _ in plan)  # still served by a until the load answers
    olds = [table.finish_move(s, m, np.zeros((2, 3)), {}) for s, m in plan]
    assert all(w == "a" for w, _ in olds) and len({k for _, k in olds}) == 3
    assert _counts(table, pool.live) == {"a": 3, "b": 3}
    assert table.plan_rebalance(pool.live, pool.generations) == []


def test_a_swap_loads_the_next_source_under_a_fresh_key_and_a_failed_move_changes_nothing():
    pool = FakePool("a")
    table = SlotTable(["first"], agents_per_scene=1)
    _carry_out(table, table.plan_placement(pool.live, pool.generations))
    key = table.slots[0].key
    move = table.plan_swap(0, "second", pool.generations)
    assert move is not None and move.key != key and move.source == "second"
    table.fail_move(0, move)
    assert table.slots[0].source == "first" and table.slots[0].key == key and table.slots[0].move is None
    move = table.plan_swap(0, "second", pool.generations)
    table.finish_move(0, move, np.ones((2, 3)), {"goal": [1, 2, 3]})
    assert table.slots[0].source == "second" and table.slots[0].metadata == {"goal": [1, 2, 3]}
    table.orphan_worker("a")
    assert table.plan_swap(0, "third", pool.generations) is None and table.slots[0].source == "third"


def test_the_revision_changes_exactly_when_a_slot_changes_worker_or_key_or_a_move_ends():
    pool = FakePool("a", "b")
    table = SlotTable(["s"] * 4, agents_per_scene=1)
    start = table.revision
    plan = table.plan_placement(pool.live, pool.generations)
    assert table.revision == start  # a plan alone serves nothing yet
    _carry_out(table, plan)
    placed = table.revision
    assert placed > start
    assert table.orphan_worker("nobody") == [] and table.revision == placed
    move = table.plan_swap(0, "t", pool.generations)
    assert table.revision == placed
    table.fail_move(0, move)
    failed = table.revision
    assert failed > placed  # the slot may be planned again
    table.fail_move(0, move)
    assert table.revision == failed  # not its move any more: nothing changed
    table.orphan_worker("a")
    assert table.revision > failed


def test_a_rejoining_worker_gets_its_share_while_swaps_are_in_flight_and_no_slot_moves_twice():
    pool = FakePool("a")
    table = SlotTable([f"s{i}" for i in range(6)], agents_per_scene=1)
    _carry_out(table, table.plan_placement(pool.live, pool.generations))
    swaps = [table.plan_swap(i, f"next{i}", pool.generations) for i in (4, 5)]   # two swap loads in flight on a
    assert all(m is not None and m.worker == "a" for m in swaps)
    pool.join("b")
    plan = table.plan_rebalance(pool.live, pool.generations)
    assert len(plan) == 3 and {s for s, _ in plan}.isdisjoint({4, 5})           # swapping slots stay put
    assert table.plan_rebalance(pool.live, pool.generations) == []              # pending moves count on b
    assert table.loads(pool.live) == {"a": 3, "b": 3}
