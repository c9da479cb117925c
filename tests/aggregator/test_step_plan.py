"""Step plans alone: which scene entries and rows each worker's request holds, on a real slot table."""

from __future__ import annotations

import numpy as np

from visfly_dist.aggregator.slots import SlotTable
from visfly_dist.aggregator.step_plan import StepPlans, plan_entries

GENS = {"a": 1, "b": 1}


def _placed(num_slots: int = 3, agents_per_scene: int = 3) -> SlotTable:
    """Slots placed on workers ``a`` and ``b`` (alternately, as placement spreads them)."""
    table = SlotTable([f"gen:s{i}" for i in range(num_slots)], agents_per_scene)
    for slot, move in table.plan_placement(["a", "b"], GENS):
        table.start_move(slot, move)
        table.finish_move(slot, move, np.zeros((2, 3)), {})
    return table


def test_entries_group_each_workers_agents_by_slot_in_request_order() -> None:
    table = _placed()
    keys = [s.key for s in table.slots]
    agents = np.array([7, 0, 4, 1, 3])  # slots 2, 0, 1, 0, 1
    plan = plan_entries(table, agents)
    workers = {w: [s.index for s in table.slots if s.worker == w] for w in ("a", "b")}
    assert sorted(plan) == ["a", "b"] and workers == {"a": [0, 2], "b": [1]}
    a, b = plan["a"], plan["b"]
    assert a.keys == [keys[0], keys[2]] and a.counts == [2, 1] and a.slots == [0, 2]
    assert a.rows.tolist() == [1, 3, 0] and a.starts == [1, 0]  # rows index ``agents``; each entry's first row
    assert b.keys == [keys[1]] and b.counts == [2] and b.rows.tolist() == [2, 4] and b.starts == [2]
    assert all(type(v) is int for v in a.counts + a.starts + a.slots)
    assert plan_entries(table, np.zeros(0, np.int64)) == {}


def test_an_armed_swap_splits_its_slot_into_the_old_and_the_incoming_scene() -> None:
    table = _placed()
    move = table.plan_swap(1, "gen:new", GENS)
    assert move is not None
    table.start_move(1, move)
    table.arm(1, move, np.zeros((2, 3)), {})
    table.take_over(np.array([4]))  # agent 4 ended its episode: its next one runs in the incoming scene
    agents = np.arange(9)
    b = plan_entries(table, agents)["b"]
    old = table.slots[1].key
    assert b.keys == [old, move.key, old] and b.counts == [1, 1, 1] and b.rows.tolist() == [3, 4, 5]
    assert b.starts == [3, 4, 5] and b.slots == [1, 1, 1]
    nxt = plan_entries(table, agents, next_episode=True)["b"]  # every next start is in the incoming scene
    assert nxt.keys == [move.key] and nxt.counts == [3] and nxt.rows.tolist() == [3, 4, 5]


def test_plans_are_kept_until_the_table_changes() -> None:
    table = _placed()
    plans = StepPlans(table)
    agents = np.arange(9)
    first = plans.get(agents)
    assert plans.get(agents.copy()) is first
    table.orphan_worker("b")
    after = plans.get(agents)
    assert after is not first and sorted(after) == ["a"]


def _reference(table: SlotTable, agents: np.ndarray, next_episode: bool) -> dict[str, list[tuple[str, list[int]]]]:
    """The plan's rule spelled out: rows by slot (stable), one entry per run of one scene."""
    out: dict[str, list[tuple[str, list[int]]]] = {}
    last = None
    for row in sorted(range(len(agents)), key=lambda r: int(table.agent_scene[agents[r]])):
        s = table.slots[int(table.agent_scene[agents[row]])]
        new = s.incoming is not None and (next_episode or bool(table.in_incoming[agents[row]]))
        worker, key = (s.incoming.move.worker, s.incoming.move.key) if new and s.incoming else (s.worker, s.key)
        if (worker, key, s.index) != last:
            out.setdefault(str(worker), []).append((key, []))
            last = (worker, key, s.index)
        out[str(worker)][-1][1].append(row)
    return out


def test_small_and_large_agent_sets_follow_one_rule_and_carry_their_wire_arrays() -> None:
    table = _placed(num_slots=12, agents_per_scene=3)
    move = table.plan_swap(4, "gen:new", GENS)
    assert move is not None
    table.start_move(4, move)
    table.arm(4, move, np.zeros((2, 3)), {})
    table.take_over(np.array([13]))
    rng = np.random.default_rng(0)
    for size in (1, 3, 16, 17, 36):  # a few agents (a step's spawn rows) and many, in and out of order
        agents = rng.permutation(36)[:size] if size % 2 else np.sort(rng.permutation(36)[:size])
        for next_episode in (False, True):
            plan = plan_entries(table, agents, next_episode)
            got = {w: [(k, e.rows[s:s + c].tolist()) for k, s, c in zip(e.keys, np.cumsum([0, *e.counts]), e.counts)]
                   for w, e in plan.items()}
            assert got == _reference(table, agents, next_episode)
            for e in plan.values():
                assert e.count_array.dtype == np.int32 and e.count_array.tolist() == e.counts
                assert e.start_array.dtype == np.int64 and e.start_array.tolist() == e.starts
                assert e.starts == [int(e.rows[s]) for s in np.cumsum([0, *e.counts[:-1]])]


def test_a_kept_plan_says_whether_its_agents_increase_and_goes_with_the_table() -> None:
    table = _placed()
    plans = StepPlans(table)
    assert plans.get(np.arange(9)).increasing and not plans.get(np.array([3, 1, 2])).increasing
    first = plans.get(np.arange(9))
    assert first["b"].count_array.tolist() == first["b"].counts
    table.orphan_worker("b")  # the table changes: the kept plan and its arrays are not used again
    after = plans.get(np.arange(9))
    assert after is not first and sorted(after) == ["a"] and after.increasing
    assert after["a"].count_array.tolist() == after["a"].counts == first["a"].counts
