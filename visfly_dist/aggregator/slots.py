"""The slot table: which scene lives on which worker, as pure data and plans (no I/O).

Agents are grouped in slots: agent ``i`` flies in slot ``i // agents_per_scene``. A slot holds one
scene source, served by one worker under one scene key. Moving a slot (to place an orphan, to
rebalance, or to swap its scene for the next source of the dataset) is a *move*: the new scene is
loaded under a fresh key while the old one keeps serving, and the slot switches when the load has
answered. A swap does not switch its slot under running episodes: once loaded it is *armed*
(:meth:`SlotTable.arm`, the slot's ``incoming`` scene), each agent takes it over when its episode
ends (:meth:`SlotTable.take_over`: its next episode starts there), and the slot switches when the
last of its agents has moved. Meanwhile the slot serves two scenes: each agent's running episode
in its own (:meth:`SlotTable.in_incoming`), and every agent's next start in the incoming one.

Plans are values: ``plan_*`` look at the table and change nothing. Only the table writes into its
slots, when told what happened: :meth:`SlotTable.start_move` (the load was sent),
:meth:`SlotTable.finish_move` / :meth:`SlotTable.fail_move` (it answered),
:meth:`SlotTable.orphan_worker`, :meth:`SlotTable.set_source`, :meth:`SlotTable.note_resets`,
:meth:`SlotTable.arm` and :meth:`SlotTable.take_over`.
:mod:`.scene_moves` carries the plans out.

Invariants:
- a slot is served (``worker`` set) only by a worker the caller said is live; :meth:`orphan_worker`
  clears every slot of a worker that died or restarted, and cancels moves towards it;
- at most one move per slot is in flight; a move records the generation of the target worker it
  was planned for, so a reply from a restarted worker is never taken for a load.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping, Sequence

import numpy as np


@dataclass
class Move:
    """A scene being loaded for a slot in the background."""

    worker: str
    key: str
    source: str
    reason: str  # "place", "rebalance" or "swap"
    generation: int


@dataclass
class Incoming:
    """A swap's scene, loaded with its spawn pools: the slot's agents take it over at their episode ends."""

    move: Move
    bounds: np.ndarray
    metadata: dict[str, Any]


@dataclass
class Slot:
    """One scene slot; ``worker`` is ``None`` while it is an orphan."""

    index: int
    source: str
    key: str
    worker: str | None = None
    generation: int = 0
    bounds: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    metadata: dict[str, Any] = field(default_factory=dict)
    resets: int = 0
    version: int = 0
    move: Move | None = None
    incoming: Incoming | None = None  # an armed swap (its ``move`` is the slot's move in flight)


class SlotTable:
    """Slots of one run and the plans that keep them served."""

    def __init__(self, sources: Sequence[str], agents_per_scene: int) -> None:
        self.agents_per_scene = int(agents_per_scene)
        self.slots = [Slot(i, source, f"s{i}v0") for i, source in enumerate(sources)]
        self.agent_scene = np.arange(len(self.slots) * self.agents_per_scene, dtype=np.int64) // self.agents_per_scene
        self.revision = 0  # bumped whenever a slot's worker or key changes or a move ends: plans over the table are stale
        self.armed = np.zeros(len(self.slots), dtype=bool)  # per slot: an incoming scene is armed
        self.in_incoming = np.zeros(len(self.agent_scene), dtype=bool)  # per agent: its episode runs in the incoming scene

    def __len__(self) -> int:
        return len(self.slots)

    def agents_of(self, slot: int) -> np.ndarray:
        """Agent indices flying in ``slot``."""
        start = slot * self.agents_per_scene
        return np.arange(start, start + self.agents_per_scene, dtype=np.int64)

    def orphans(self) -> list[Slot]:
        return [s for s in self.slots if s.worker is None]

    def loads(self, live: Iterable[str]) -> dict[str, int]:
        """Slots served or being loaded per live worker (a move counts on its target)."""
        loads = {w: 0 for w in live}
        for s in self.slots:
            if s.move is not None and s.move.worker in loads:
                loads[s.move.worker] += 1
            elif s.worker in loads:
                loads[s.worker] += 1
        return loads

    def orphan_worker(self, worker_id: str) -> list[int]:
        """Forget ``worker_id``: its slots become orphans, moves towards it are cancelled. An armed
        swap there is dropped; if some agents already fly in it, the slot is placed again with its
        source (the others' episodes change scene: :meth:`cut_by_orphaning` says whose)."""
        for s, _, moved in self._takeovers_on(worker_id):
            if moved.any() and s.incoming is not None:
                s.source = s.incoming.move.source
            self._disarm(s)
        lost = []
        for s in self.slots:
            if s.worker == worker_id:
                s.worker = None
                lost.append(s.index)
            if s.move is not None and s.move.worker == worker_id:
                s.move = None
        if lost:
            self.revision += 1
        return lost

    def plan_placement(self, live: Sequence[str], generations: dict[str, int],
                       lacking: Mapping[str, set[str]] | None = None) -> list[tuple[int, Move]]:
        """Moves that would put every orphan without a move in flight on the least-loaded live workers
        that have its source (``lacking``: source -> workers without its file; were every live worker
        among them, the load is asked anyway, and its failure drops the source)."""
        if not live:
            return []
        loads = self.loads(live)
        plan = []
        for s in self.slots:
            if s.worker is None and s.move is None:
                able = [w for w in live if lacking is None or w not in lacking.get(s.source, ())] or live
                target = min(able, key=lambda w: (loads[w], w))
                loads[target] += 1
                plan.append((s.index, self._move(s, target, s.source, "place", generations)))
        return plan

    def plan_rebalance(self, live: Sequence[str], generations: dict[str, int],
                       lacking: Mapping[str, set[str]] | None = None) -> list[tuple[int, Move]]:
        """Moves from the busiest to the idlest worker while their loads would differ by more than one
        slot (never a slot whose source the idlest lacks: ``lacking`` as in :meth:`plan_placement`)."""
        lacking = lacking or {}
        loads = self.loads(live)
        plan: list[tuple[int, Move]] = []
        moving = {s.index for s in self.slots if s.move is not None}
        while len(loads) > 1:
            busiest = max(loads, key=lambda w: (loads[w], w))
            idlest = min(loads, key=lambda w: (loads[w], w))
            if loads[busiest] - loads[idlest] <= 1:
                break
            candidates = [s for s in reversed(self.slots) if s.worker == busiest and s.index not in moving
                          and idlest not in lacking.get(s.source, ())]
            if not candidates:
                break
            slot = candidates[0]
            moving.add(slot.index)
            plan.append((slot.index, self._move(slot, idlest, slot.source, "rebalance", generations)))
            loads[busiest] -= 1
            loads[idlest] += 1
        return plan

    def plan_swap(self, slot: int, source: str, generations: dict[str, int]) -> Move | None:
        """The move that loads ``source`` for ``slot`` on the worker serving it; ``None`` while it has
        none (then :meth:`set_source`: it is placed with the new source when a worker takes it)."""
        s = self.slots[slot]
        if s.worker is None:
            return None
        return self._move(s, s.worker, source, "swap", generations)

    def cut_by_orphaning(self, worker_id: str) -> np.ndarray:
        """Agents whose running episode would change scene if ``worker_id`` were orphaned now: those
        not yet moved into an armed swap there that some of their slot's agents already fly in."""
        out = np.zeros(len(self.agent_scene), dtype=bool)
        for _, agents, moved in self._takeovers_on(worker_id):
            if moved.any():
                out[agents[~moved]] = True
        return out

    def _takeovers_on(self, worker_id: str) -> list[tuple[Slot, np.ndarray, np.ndarray]]:
        """``(slot, its agents, which of them moved)`` of each armed swap on ``worker_id``."""
        out = []
        for s in self.slots:
            if s.incoming is not None and s.incoming.move.worker == worker_id:
                agents = self.agents_of(s.index)
                out.append((s, agents, self.in_incoming[agents].copy()))
        return out

    def arm(self, slot: int, move: Move, bounds: np.ndarray, metadata: dict[str, Any]) -> None:
        """``slot``'s swap ``move`` is loaded and its spawn pools are in: its agents take it over at
        their episode ends (:meth:`take_over`)."""
        s = self.slots[slot]
        s.incoming = Incoming(move, np.asarray(bounds, dtype=np.float64).reshape(2, 3), dict(metadata))
        self.armed[slot] = True
        self.revision += 1

    def take_over(self, agents: np.ndarray) -> tuple[np.ndarray, list[int]]:
        """Agents ``agents`` ended their episodes: those of armed slots start the next one in the
        incoming scene. Returns the agents that moved and the slots all of whose agents have moved
        (to :meth:`finish_move` with the incoming scene)."""
        slot_of = self.agent_scene[agents]
        moving = agents[self.armed[slot_of] & ~self.in_incoming[agents]]
        if not len(moving):
            return moving, []
        self.in_incoming[moving] = True
        self.revision += 1
        slots = np.unique(self.agent_scene[moving]).tolist()
        return moving, [s for s in slots if self.in_incoming[self.agents_of(s)].all()]

    def _disarm(self, s: Slot) -> None:
        s.incoming = None
        self.armed[s.index] = False
        self.in_incoming[self.agents_of(s.index)] = False
        self.revision += 1

    def scene_of(self, agent: int, next_episode: bool = False) -> tuple[str | None, str, str, np.ndarray, dict[str, Any]]:
        """``(worker, key, source, bounds, metadata)`` of the scene agent ``agent`` flies in (its
        running episode), or, with ``next_episode``, where its next episode starts."""
        s = self.slots[int(self.agent_scene[agent])]
        if s.incoming is not None and (next_episode or self.in_incoming[agent]):
            m = s.incoming.move
            return m.worker, m.key, m.source, s.incoming.bounds, s.incoming.metadata
        return s.worker, s.key, s.source, s.bounds, s.metadata

    def agent_bounds(self) -> np.ndarray:
        """``(N, 2, 3)`` float64 flight box of the scene of each agent's running episode."""
        bounds = np.stack([s.bounds for s in self.slots]).astype(np.float64)[self.agent_scene]
        for agent in np.flatnonzero(self.in_incoming).tolist():
            bounds[agent] = self.scene_of(agent)[3]
        return bounds

    def agent_metadata(self, agent: int) -> dict[str, Any]:
        """The metadata of the scene of agent ``agent``'s running episode, plus its ``source``."""
        _, _, source, _, metadata = self.scene_of(agent)
        meta = dict(metadata)
        meta.setdefault("source", source)
        return meta

    def agent_sources(self) -> list[str]:
        """The source of the scene of each agent's running episode."""
        sources = [self.slots[slot].source for slot in self.agent_scene.tolist()]
        for agent in np.flatnonzero(self.in_incoming).tolist():
            sources[agent] = self.scene_of(agent)[2]
        return sources

    def _move(self, slot: Slot, worker: str, source: str, reason: str, generations: dict[str, int]) -> Move:
        return Move(worker, f"s{slot.index}v{slot.version + 1}", source, reason, generations.get(worker, 0))

    def start_move(self, slot: int, move: Move) -> None:
        """A planned move is under way (its load was sent); the slot serves its old scene until
        :meth:`finish_move`. Start each planned move once, and before planning again."""
        s = self.slots[slot]
        s.version += 1
        s.move = move

    def set_source(self, slot: int, source: str) -> None:
        """An orphan takes another source (a swap while it had no worker, or its source was dropped)."""
        self.slots[slot].source = source

    def note_resets(self, slot: int, count: int, every: int, may_start: bool = True) -> bool:
        """Count ``count`` episode resets in ``slot``. True when it is due for a swap (``every`` resets
        so far, no move in flight, and ``may_start``: its worker takes another load now); its count
        starts again then. A slot due but held back stays due: its next reset asks again."""
        s = self.slots[slot]
        s.resets += count
        if s.resets >= every and s.move is None and may_start:
            s.resets = 0
            return True
        return False

    def finish_move(self, slot: int, move: Move, bounds: np.ndarray, metadata: dict[str, Any]) -> tuple[str | None, str]:
        """The load answered: the slot switches. Returns the (worker, key) the old scene can be unloaded from."""
        s = self.slots[slot]
        old = (s.worker, s.key)
        s.worker, s.key, s.source, s.generation = move.worker, move.key, move.source, move.generation
        s.bounds = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
        s.metadata = dict(metadata)
        s.move = None
        if s.incoming is not None:
            self._disarm(s)
        self.revision += 1
        return old

    def fail_move(self, slot: int, move: Move) -> None:
        """The load failed; the slot keeps what it had (an orphan is placed again later)."""
        if self.slots[slot].move is move:
            self.slots[slot].move = None
            self.revision += 1

    def by_worker(self, slots: Iterable[int]) -> dict[str, list[int]]:
        """Served slots of ``slots`` grouped by worker (orphans left out)."""
        out: dict[str, list[int]] = {}
        for i in slots:
            worker = self.slots[i].worker
            if worker is not None:
                out.setdefault(worker, []).append(i)
        return out
