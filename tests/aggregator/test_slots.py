"""The slot table alone: placement, orphaning, rebalancing and swaps as plans, against a fake pool.

Plans are values: planning changes nothing, and the table changes only when told a move started
(``start_move``), ended (``finish_move`` / ``fail_move``) or a worker left (``orphan_worker``)."""

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


def _start(table: SlotTable, plan) -> None:
    """Every load of ``plan`` is sent."""
    for slot, move in plan:
        table.start_move(slot, move)


def _carry_out(table: SlotTable, plan) -> None:
    """Every load of ``plan`` is sent and answers: each planned slot switches."""
    _start(table, plan)
    for slot, move in plan:
        table.finish_move(slot, move, np.zeros((2, 3)), {})


def _state(table: SlotTable) -> list[tuple]:
    return [(s.worker, s.key, s.source, s.version, s.resets, s.move) for s in table.slots]


def _counts(table: SlotTable, live) -> dict[str, int]:
    return {w: sum(s.worker == w for s in table.slots) for w in live}


def test_placement_spreads_orphans_over_the_least_loaded_workers():
    pool = FakePool("a", "b", "c")
    table = SlotTable([f"gen:x?seed={i}" for i in range(7)], agents_per_scene=2)
    before = _state(table)
    plan = table.plan_placement(pool.live, pool.generations)
    assert len(plan) == 7 and _state(table) == before                         # a plan is a value: nothing changed
    assert table.plan_placement(pool.live, pool.generations) == plan          # so planning again gives the same plan
    _start(table, plan)
    assert all(table.slots[s].move is m for s, m in plan)
    assert table.plan_placement(pool.live, pool.generations) == []  # moves in flight are not planned twice
    for slot, move in plan:
        table.finish_move(slot, move, np.zeros((2, 3)), {})
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
    _start(table, plan)
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
    table.start_move(0, move)
    table.fail_move(0, move)
    assert table.slots[0].source == "first" and table.slots[0].key == key and table.slots[0].move is None
    again = table.plan_swap(0, "second", pool.generations)
    assert again is not None and again.key != move.key  # a fresh key: a late reply to the failed load names the old one
    table.start_move(0, again)
    table.finish_move(0, again, np.ones((2, 3)), {"goal": [1, 2, 3]})
    assert table.slots[0].source == "second" and table.slots[0].metadata == {"goal": [1, 2, 3]}
    table.orphan_worker("a")
    assert table.plan_swap(0, "third", pool.generations) is None and table.slots[0].source == "second"
    table.set_source(0, "third")  # no worker to load it on: placed with the new source later
    (placed,) = table.plan_placement(["b"], {"b": 1})
    assert placed[1].source == "third"


def test_resets_make_a_slot_due_for_a_swap_every_so_many_and_never_while_it_moves():
    pool = FakePool("a")
    table = SlotTable(["s", "t"], agents_per_scene=2)
    _carry_out(table, table.plan_placement(pool.live, pool.generations))
    assert not table.note_resets(0, 2, every=3) and table.note_resets(0, 1, every=3)  # the third reset: due
    assert not table.note_resets(0, 2, every=3)                                       # counting again from zero
    move = table.plan_swap(0, "u", pool.generations)
    table.start_move(0, move)
    assert not table.note_resets(0, 5, every=3)                                       # not while its swap loads
    table.finish_move(0, move, np.zeros((2, 3)), {})
    assert table.note_resets(0, 1, every=3)                                           # due at its next reset after the move
    assert not table.note_resets(1, 2, every=3)                                       # per slot
    assert not table.note_resets(1, 1, every=3, may_start=False)                      # due, but held back
    assert table.slots[1].resets == 3 and table.note_resets(1, 1, every=3)            # still due: it swaps at its next reset


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
    table.start_move(0, move)
    assert table.revision == placed  # a started move serves nothing yet
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
    swaps = [(i, table.plan_swap(i, f"next{i}", pool.generations)) for i in (4, 5)]   # two swap loads in flight on a
    assert all(m is not None and m.worker == "a" for _, m in swaps)
    _start(table, swaps)
    pool.join("b")
    plan = table.plan_rebalance(pool.live, pool.generations)
    assert len(plan) == 3 and {s for s, _ in plan}.isdisjoint({4, 5})           # swapping slots stay put
    _start(table, plan)
    assert table.plan_rebalance(pool.live, pool.generations) == []              # pending moves count on b
    assert table.loads(pool.live) == {"a": 3, "b": 3}


def _armed_swap(table: SlotTable, pool: FakePool, slot: int, source: str):
    move = table.plan_swap(slot, source, pool.generations)
    table.start_move(slot, move)
    table.arm(slot, move, np.ones((2, 3)), {"goal": [1, 2, 3]})
    return move


def test_an_armed_swap_is_taken_over_agent_by_agent_and_switches_with_the_last():
    pool = FakePool("a")
    table = SlotTable(["old0", "old1"], agents_per_scene=2)
    _carry_out(table, table.plan_placement(pool.live, pool.generations))
    _armed_swap(table, pool, 0, "new0")
    assert table.agent_sources() == ["old0", "old0", "old1", "old1"]
    moved, complete = table.take_over(np.array([1, 2]))      # agent 2's slot has no swap
    assert moved.tolist() == [1] and complete == []
    assert table.agent_sources() == ["old0", "new0", "old1", "old1"] and table.agent_metadata(1)["goal"] == [1, 2, 3]
    assert table.scene_of(0, next_episode=True)[2] == "new0"  # agent 0's next start lies in the new scene
    moved, complete = table.take_over(np.array([0, 1]))      # agent 1 moved already
    assert moved.tolist() == [0] and complete == [0]


def test_a_worker_lost_mid_takeover_cuts_only_the_agents_not_yet_moved():
    pool = FakePool("a")
    table = SlotTable(["old0", "old1"], agents_per_scene=2)
    _carry_out(table, table.plan_placement(pool.live, pool.generations))
    _armed_swap(table, pool, 0, "new0")
    _armed_swap(table, pool, 1, "new1")
    table.take_over(np.array([1]))
    assert table.cut_by_orphaning("a").tolist() == [True, False, False, False]  # slot 1: nobody moved, nobody cut
    table.orphan_worker("a")
    assert [s.source for s in table.slots] == ["new0", "old1"] and not table.armed.any() and not table.in_incoming.any()


def test_a_start_up_plan_is_logged_as_one_short_line_per_worker_and_reason():
    from visfly_dist.aggregator.scene_moves import _plan_summary
    from visfly_dist.aggregator.slots import Move

    plan = [(i, Move(f"local-{i % 2}", f"s{i}v1", "gen:garage", "place", 1)) for i in range(256)]
    plan.append((7, Move("local-1", "s7v2", "gen:garage", "swap", 1)))
    summary = _plan_summary(plan)
    assert summary == ("128 slots (0, 2, 4, 6, 8, 10, 12, 14, ...) on local-0 (place); "
                       "128 slots (1, 3, 5, 7, 9, 11, 13, 15, ...) on local-1 (place); slot 7 on local-1 (swap)")


def test_a_source_a_worker_lacks_is_placed_and_rebalanced_onto_the_others_only():
    pool = FakePool("a", "b")
    table = SlotTable(["common", "rare", "common", "rare"], agents_per_scene=1)
    lacking = {"rare": {"b"}}
    plan = table.plan_placement(pool.live, pool.generations, lacking)
    assert [(s, m.worker) for s, m in plan] == [(0, "a"), (1, "a"), (2, "b"), (3, "a")]
    _carry_out(table, plan)
    # a holds 3, b 1: the rebalance may give b a "common" slot, never a "rare" one
    moves = table.plan_rebalance(pool.live, pool.generations, lacking)
    assert [(table.slots[s].source, m.worker) for s, m in moves] == [("common", "b")]
    _carry_out(table, moves)
    assert all(s.worker == "a" for s in table.slots if s.source == "rare")
    assert _counts(table, pool.live) == {"a": 2, "b": 2}
    # were every live worker to lack it, it is asked anyway (its failure drops the source)
    every = SlotTable(["rare"], agents_per_scene=1)
    assert [m.worker for _, m in every.plan_placement(pool.live, pool.generations, {"rare": {"a", "b"}})] == ["a"]
