"""Step plans: which scene entries, and which agents' rows, each worker's request of a step holds.

A step sends one request per worker: the scene keys it serves for the agents stepped, an agent
count per key, and those agents' poses in request order (grouped by slot; while a swap takes a slot
over, its agents in the old and in the incoming scene are entries of their own, each a run of
consecutive rows, so that images can be written in place). The plan depends only
on the agents and on the slot table, so :class:`StepPlans` keeps it while the table's revision is
unchanged: a training loop steps the same agents (all, or each of its groups) on the same workers
every time. Each entry list also comes as the arrays a request carries (``count_array``,
``start_array``), made once with the plan, not per step.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from visfly_dist.aggregator.inputs import increasing
from visfly_dist.aggregator.slots import SlotTable

MAX_CACHED_PLANS = 8
"""Step plans kept per slot-table revision: one per agent set stepped (all agents, or each group)."""

__all__ = ["Plan", "StepPlans", "WorkerEntries", "plan_entries"]


@dataclass(frozen=True)
class WorkerEntries:
    """One worker's scene entries for a set of agents (the lists run over its entries)."""

    keys: list[str] = field(default_factory=list)      # scene key of each entry
    counts: list[int] = field(default_factory=list)    # agents in each entry
    rows: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # the agents' rows, in request order
    slots: list[int] = field(default_factory=list)     # slot of each entry
    starts: list[int] = field(default_factory=list)    # each entry's first row
    count_array: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))  # counts as the wire's int32
    start_array: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # starts as an int64 array


class Plan(dict[str, WorkerEntries]):
    """:func:`plan_entries` of one agent set, per worker, and whether the agents are in increasing
    order (then each entry's rows are one run: images can be laid out in observation order)."""

    increasing: bool = False


def plan_entries(table: SlotTable, agents: np.ndarray, next_episode: bool = False) -> dict[str, WorkerEntries]:
    """Per worker, the entries of ``agents`` (rows index ``agents``) in the scenes of their running
    episodes, or with ``next_episode`` where their next episodes start; agents of orphan slots are
    left out."""
    n = len(agents)
    if n == 0:
        return {}
    slot_of = table.agent_scene[agents]
    order = np.argsort(slot_of, kind="stable")
    incoming = table.in_incoming[agents] | table.armed[slot_of] if next_episode else table.in_incoming[agents]
    code = (slot_of * 2 + incoming)[order]
    cuts = (np.flatnonzero(code[1:] != code[:-1]) + 1).tolist()  # plain lists: a few entries cost no NumPy call each
    codes, firsts = code.tolist(), order.tolist()
    out: dict[str, tuple[list[str], list[int], list[int], list[int], list[int]]] = {}
    for start, end in zip([0, *cuts], [*cuts, n]):
        slot, new = divmod(codes[start], 2)
        s = table.slots[slot]
        worker, key = (s.incoming.move.worker, s.incoming.move.key) if new and s.incoming is not None else (s.worker, s.key)
        if worker is None:
            continue
        keys, cnts, rows, served, first = out.setdefault(worker, ([], [], [], [], []))
        keys.append(key)
        cnts.append(end - start)
        rows.extend(firsts[start:end])
        served.append(slot)
        first.append(firsts[start])
    return {w: WorkerEntries(k, c, np.array(r, np.int64), sl, f, np.array(c, np.int32), np.array(f, np.int64))
            for w, (k, c, r, sl, f) in out.items()}


class StepPlans:
    """:func:`plan_entries` of the agents stepped, kept while the slot table is unchanged."""

    def __init__(self, table: SlotTable) -> None:
        self._table = table
        self._plans: dict[bytes, Plan] = {}
        self._revision = -1

    def get(self, agents: np.ndarray) -> Plan:
        key = agents.tobytes()
        if self._revision != self._table.revision:
            self._plans.clear()
            self._revision = self._table.revision
        plan = self._plans.get(key)
        if plan is None:
            if len(self._plans) >= MAX_CACHED_PLANS:
                self._plans.clear()
            plan = self._plans[key] = Plan(plan_entries(self._table, agents))
            plan.increasing = increasing(agents)
        return plan
