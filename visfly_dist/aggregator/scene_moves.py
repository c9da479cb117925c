"""Scene moves carried out in the background: loads, switches, unloads, stale scenes, reconciliation.

The slot table (:mod:`.slots`) plans moves; this module sends them over the pool and keeps what
follows from them, between steps and never inside one:

- **loads**: one ``load_scene`` request per move, under the move's fresh key, while the old key
  keeps serving (:meth:`SceneMoves.send_loads`);
- **switches**: a loaded swap first waits for its new scene's spawn pools (a
  :class:`PendingSwitch`), so resets never wait for them; then it is armed and the slot's agents
  take it over at their episode ends (:meth:`SceneMoves.take_over`); the slot switches
  (:meth:`SceneMoves.switch`, the one place a slot changes scene) when the last has moved, so no
  running episode changes scene;
- **unloads**: the old key is unloaded :data:`UNLOAD_DELAY_COLLECTS` collects after the switch,
  when no request in flight can still name it;
- **stale scenes**: keys a worker may still hold but no longer serves (its slots were orphaned, a
  load's reply was lost, an unload got no reply) are unloaded when it is next seen live;
- **reconciliation**: each worker that (re)appears is asked which scenes it holds, and those the
  run does not know of are unloaded;
- **back-off**: a worker that answered ``overloaded`` gets no new scene for a while;
- **dropped sources**: a source that cannot load leaves the dataset.

Requests go out at once and come back as jobs (:class:`LoadJob`, :class:`UnloadJob`,
:class:`ReconcileJob`) that the aggregator keeps with its other background requests and hands back
here when they finish. Which error does what is the aggregator's failure policy, not this module's.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from visfly_dist.aggregator.config import PoolConfig
from visfly_dist.aggregator.dataset import SceneDataset
from visfly_dist.aggregator.pool import Pending, Reply, WorkerPool
from visfly_dist.aggregator.slots import Move, SlotTable
from visfly_dist.aggregator.spawn_pools import PoolKey, SpawnSpec
from visfly_dist.errors import ConfigError, RemoteError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.messages import Health, LoadScene, UnloadScene

log = logging.getLogger(__name__)

LOAD_QUEUE_ALLOWANCE_S = 2.0
"""Seconds added to a load's deadline for every load queued before it on the same worker (a garage
takes about 0.3 s on one core): 256 scenes placed on 2 workers at start-up must not time out
behind each other."""

UNLOAD_DELAY_COLLECTS = 2
"""Collects between a switch and the unload of the old key: no request in flight names it then."""

OVERLOADED_BACKOFF_S = (1.0, 30.0)
"""First and longest wait before a worker that answered ``overloaded`` (or let a load time out while
it answers) is given a new scene again."""

SWAP_LOADS_PER_WORKER = 2
"""Loads one worker may have unanswered when a swap asks it for another. Once steps are served a
worker makes one scene at a time, niced (:mod:`visfly_dist.scene_worker.loads`): one load running
and one queued keep it busy. Swaps asked for faster than that (short episodes: a slot is due every
``swap_every_resets`` resets) would queue more and more loads on it, each waiting behind the others
until one times out (measured: 256 agents stepped with random actions on 2 cores, a load request
unanswered for 60 s after 1,400 steps). A due slot held back swaps at a later reset instead."""

__all__ = ["LoadJob", "PendingSwitch", "ReconcileJob", "SceneMoves", "UnloadJob"]


@dataclass
class LoadJob:
    """A ``load_scene`` request in flight, for ``move`` of ``slot``."""

    pending: Pending
    slot: int
    move: Move


@dataclass
class UnloadJob:
    """An ``unload_scene`` request in flight: ``key`` on ``worker``."""

    pending: Pending
    worker: str
    key: str


@dataclass
class ReconcileJob:
    """A health request in flight, asking ``worker`` (seen at ``generation``) which scenes it holds."""

    pending: Pending
    worker: str
    generation: int


@dataclass
class PendingSwitch:
    """A swap whose scene has loaded, waiting for the new scene's spawn pools before it switches."""

    move: Move
    bounds: Any  # the load reply's bounds and metadata, kept for the switch
    metadata: dict[str, Any]
    waiting: set[SpawnSpec]  # distributions whose pool for the new scene has not arrived yet


class SceneMoves:
    """The background side of the slot table: requests for moves, and what they leave to clean up.

    Args:
        pool: where requests go.
        table: the run's slot table.
        dataset: where the next source of a swap, or of a slot whose source was dropped, comes from.
        config: deadlines (``startup_timeout_s`` for loads, ``step_timeout_s`` for the rest).
        cameras, drone_radius, multi_agent: what every ``load_scene`` request asks for.
        run_id: for the log.
    """

    def __init__(self, pool: WorkerPool, table: SlotTable, dataset: SceneDataset, config: PoolConfig,
                 cameras: Sequence[CameraSpec], drone_radius: float, multi_agent: bool, run_id: str) -> None:
        self._pool = pool
        self._table = table
        self._dataset = dataset
        self._config = config
        self._cameras = tuple(cameras)
        self._drone_radius = drone_radius
        self._multi_agent = multi_agent
        self._run_id = run_id
        self._collects = 0
        self._unloads: list[tuple[int, str, str]] = []  # (due collect, worker, key)
        self.stale: dict[str, set[str]] = {}  # worker -> keys it may still hold but no longer serves
        self._reconciled: dict[str, int] = {}  # worker -> the generation whose held scenes were checked
        self._full: dict[str, tuple[float, float]] = {}  # worker -> (no new scene before, backoff) after overloaded
        self._full_why: dict[str, str] = {}  # worker -> why it backs off (the last time it did)
        self.lacking: dict[str, set[str]] = {}  # source -> workers without its file under their scene roots
        self._switches: dict[int, PendingSwitch] = {}  # slot -> its loaded swap, waiting for spawn pools
        self._switched = np.zeros(len(table.agent_scene), dtype=bool)  # scene changed under a running episode
        self._next_scene = np.zeros(len(table.agent_scene), dtype=bool)  # next episode starts in an armed swap

    # ----- loads and switches ----------------------------------------------------------------

    def send_loads(self, plan: Sequence[tuple[int, Move]]) -> list[LoadJob]:
        """Start every move of ``plan`` (a plan of the slot table) and send its load: the one place
        moves start."""
        jobs: list[LoadJob] = []
        queued: dict[str, int] = {}  # loads sent to each worker so far in this batch
        for slot, move in plan:
            self._table.start_move(slot, move)
            ahead = queued.get(move.worker, 0)
            queued[move.worker] = ahead + 1
            # a worker loads one scene at a time: this load may first wait for the ones ahead of it
            timeout_s = self._config.startup_timeout_s + ahead * LOAD_QUEUE_ALLOWANCE_S
            request = LoadScene(move.key, move.source, self._cameras, self._drone_radius, self._multi_agent).to_message()
            (pending,) = self._pool.send([(move.worker, request)], timeout_s)
            jobs.append(LoadJob(pending, slot, move))
        if plan:
            log.info("run %s: loading in the background: %s", self._run_id, _plan_summary(plan))
        return jobs

    def start_swaps(self, resets: np.ndarray, every: int,
                    workers: Callable[[], tuple[dict[str, int], dict[str, int]]]) -> list[LoadJob]:
        """Count ``resets`` (per slot); a slot due for a swap starts loading the dataset's next source,
        unless its worker has :data:`SWAP_LOADS_PER_WORKER` loads not taken in yet or backs off (it
        swaps at a later reset then). ``workers`` gives the live workers' generations and their loads
        in flight; it is asked only when some slot is due (most resets: none is)."""
        slots = self._table.slots
        counted = np.flatnonzero(resets).tolist()
        if not any(slots[i].move is None and slots[i].resets + int(resets[i]) >= every for i in counted):
            for slot in counted:
                self._table.note_resets(slot, int(resets[slot]), every)  # none is due: only counted
            return []
        generations, loading = workers()
        plan = []
        now = time.monotonic()
        asked = dict(loading)  # this batch's swaps included
        # the most overdue first: where a worker takes fewer loads than are due, none waits for ever
        for slot in sorted(counted, key=lambda i: -(slots[i].resets + int(resets[i]))):
            worker = slots[slot].worker
            may_start = worker is None or (asked.get(worker, 0) < SWAP_LOADS_PER_WORKER
                                           and self._full.get(worker, (0.0, 0.0))[0] <= now)
            if self._table.note_resets(slot, int(resets[slot]), every, may_start):
                source = self._dataset.next_source()
                if worker in self.lacking.get(source, ()):  # its file is not there: the slot swaps later
                    continue
                move = self._table.plan_swap(slot, source, generations)
                if move is None:
                    self._table.set_source(slot, source)
                else:
                    plan.append((slot, move))
                    asked[move.worker] = asked.get(move.worker, 0) + 1
        return self.send_loads(plan)

    def await_pools(self, slot: int, switch: PendingSwitch) -> None:
        """``slot``'s swap has loaded; it switches once :meth:`pool_ready` has seen all its pools."""
        self._switches[slot] = switch

    def pool_ready(self, key: PoolKey) -> None:
        """A spawn pool arrived; the last one a loaded swap waited for switches its slot."""
        switch = self._switches.get(key.slot)
        if switch is not None and switch.move.source == key.source:
            switch.waiting.discard(key.spec)
            if not switch.waiting:
                del self._switches[key.slot]
                self.switch(key.slot, switch.move, switch.bounds, switch.metadata)

    def cancel_switch(self, slot: int) -> Move | None:
        """A spawn pool of ``slot`` failed: a loaded swap waiting there is not used (its key is unloaded
        later). Returns that swap's move (``None``: no swap waited)."""
        switch = self._switches.pop(slot, None)
        if switch is None:
            return None
        self._table.fail_move(slot, switch.move)
        self.mark_stale(switch.move.worker, switch.move.key)
        return switch.move

    @property
    def switching(self) -> bool:
        """Whether a loaded swap waits for its spawn pools."""
        return bool(self._switches)

    def switch(self, slot: int, move: Move, bounds: Any, metadata: dict[str, Any]) -> None:
        """``move`` of ``slot`` is ready. A placed or rebalanced scene (the same source) serves at
        once; a swapped-in one is armed: the slot's agents take it over at their episode ends."""
        if move.reason == "swap":
            self._table.arm(slot, move, bounds, metadata)
            self._next_scene[self._table.agents_of(slot)] = True
            return
        self._finish(slot, move, bounds, metadata)

    def take_over(self, agents: np.ndarray) -> np.ndarray:
        """Agents ``agents`` ended their episodes: those of armed slots move into the incoming
        scene (returned); a slot whose agents have all moved switches to it."""
        moved, complete = self._table.take_over(agents)
        for slot in complete:
            incoming = self._table.slots[slot].incoming
            assert incoming is not None
            self._finish(slot, incoming.move, incoming.bounds, incoming.metadata)
            log.info("run %s: slot %d now holds %s", self._run_id, slot, incoming.move.source)
        return moved

    def _finish(self, slot: int, move: Move, bounds: Any, metadata: dict[str, Any]) -> None:
        """``slot`` now serves ``move``'s scene (the one place a slot changes scene); its old key is
        unloaded a little later."""
        old_worker, old_key = self._table.finish_move(slot, move, bounds, metadata)
        if old_worker is not None and old_key != move.key:
            self._unloads.append((self._collects + UNLOAD_DELAY_COLLECTS, old_worker, old_key))

    def take_switched(self) -> np.ndarray:
        """``(N,)`` bool: agents whose scene changed under their running episode since the last call
        (only a worker lost while its slot's agents were taking a swap over does that)."""
        out, self._switched = self._switched, np.zeros_like(self._switched)
        return out

    def take_next_scene(self) -> np.ndarray:
        """``(N,)`` bool: agents whose next episode will start in a newly armed swap (their next start
        must be drawn there) since the last call."""
        out, self._next_scene = self._next_scene, np.zeros_like(self._next_scene)
        return out

    # ----- unloads and stale scenes ----------------------------------------------------------

    def note_collect(self) -> None:
        """A step was collected: unloads wait for a number of these."""
        self._collects += 1

    def due_unloads(self) -> list[tuple[str, str]]:
        """The ``(worker, key)`` of old scenes that no request in flight can name any more."""
        due = [(w, k) for c, w, k in self._unloads if c <= self._collects]
        self._unloads = [u for u in self._unloads if u[0] > self._collects]
        return due

    def send_unloads(self, targets: Sequence[tuple[str, str]]) -> list[UnloadJob]:
        """Ask each ``(worker, key)`` to unload; one that gets no reply is retried when the worker is
        next seen live (:meth:`finish_unload`)."""
        requests = [(w, UnloadScene(k).to_message()) for w, k in targets]
        sent = self._pool.send(requests, self._config.step_timeout_s) if requests else []
        return [UnloadJob(pending, worker, key) for (worker, key), pending in zip(targets, sent)]

    def finish_unload(self, job: UnloadJob, reply: Reply) -> None:
        if reply.failure is not None:  # lost on the way (a flapping link): try again later
            self.mark_stale(job.worker, job.key)

    def mark_stale(self, worker: str, key: str) -> None:
        """``worker`` may hold ``key`` but does not serve it: unload it when the worker is next seen."""
        self.stale.setdefault(worker, set()).add(key)

    def orphan(self, worker: str, reason: str) -> None:
        """Orphan ``worker``'s slots; remember their keys, to unload them if it comes back with them."""
        for slot in self._table.slots:
            if slot.worker == worker:
                self.mark_stale(worker, slot.key)
            if slot.incoming is not None and slot.incoming.move.worker == worker:
                self.mark_stale(worker, slot.incoming.move.key)
        self._switched |= self._table.cut_by_orphaning(worker)
        left = self._table.orphan_worker(worker)
        if len(left):
            log.warning("run %s: %s left worker %s (%s)", self._run_id, _slot_list(left), worker, reason)

    def held(self) -> list[tuple[str, str]]:
        """Every ``(worker, key)`` a worker may hold for this run: served, being loaded or armed for
        a slot (an armed swap's move is its slot's move), due to be unloaded, or stale."""
        out = {(s.worker, s.key) for s in self._table.slots if s.worker is not None}
        out |= {(s.move.worker, s.move.key) for s in self._table.slots if s.move is not None}
        out |= {(w, k) for _, w, k in self._unloads}
        out |= {(w, k) for w, keys in self.stale.items() for k in keys}
        return sorted(out)

    def take_stale(self, live: Sequence[str]) -> list[tuple[str, str]]:
        """A worker that dropped off the network and rejoined still holds scenes it no longer serves:
        the ``(worker, key)`` to unload (a restarted one answers ``unknown_scene``, which is fine)."""
        back = [w for w in live if w in self.stale]
        return [(w, k) for w in back for k in sorted(self.stale.pop(w))]

    def reconcile(self, generations: dict[str, int]) -> list[ReconcileJob]:
        """Ask each worker that (re)appeared which scenes it holds (:meth:`finish_reconcile` unloads
        those the run does not know of). Replies lost in an outage (a router killed while loads were
        in flight) leave such scenes behind."""
        due = [w for w, g in generations.items() if self._reconciled.get(w) != g]
        for w in due:
            self._reconciled[w] = generations[w]
        sent = self._pool.send([(w, Health().to_message()) for w in due], self._config.step_timeout_s) if due else []
        return [ReconcileJob(pending, w, generations[w]) for w, pending in zip(due, sent)]

    def finish_reconcile(self, job: ReconcileJob, reply: Reply, unloading: set[str]) -> list[tuple[str, str]]:
        """The ``(worker, key)`` to unload: what the worker holds that the run neither serves, moves
        to, nor unloads already (``unloading``: keys of unloads in flight to it)."""
        worker = job.worker
        if reply.message is None:  # asked again when it is next seen (its failures are handled where it serves)
            if self._reconciled.get(worker) == job.generation:
                del self._reconciled[worker]
            return []
        known = {k for w, k in self.held() if w == worker} | unloading
        unknown = sorted((set(reply.message.get("scenes", [])) | set(reply.message.get("loading", []))) - known)
        if not unknown:
            return []
        log.warning("run %s: worker %s holds scenes %s that the run does not serve (left by an earlier run "
                    "with this run id that could not unload them, or their load replies were lost); unloading them",
                    self._run_id, worker, unknown)
        return [(worker, k) for k in unknown]

    # ----- workers that are full, sources that cannot load -----------------------------------

    def back_off(self, worker: str, why: str) -> None:
        """A worker that is full (``overloaded``) or slower at loading than it is asked to load gets
        no new scene for a while (doubling each time)."""
        _, wait = self._full.get(worker, (0.0, OVERLOADED_BACKOFF_S[0] / 2))
        wait = min(2 * wait, OVERLOADED_BACKOFF_S[1])
        self._full[worker] = (time.monotonic() + wait, wait)
        self._full_why[worker] = why
        log.warning("run %s: worker %s %s; no new scene for it for %g s", self._run_id, worker, why, wait)

    def placeable(self, live: Sequence[str]) -> list[str]:
        """The live workers that may take new scenes now (not backing off after ``overloaded``)."""
        now = time.monotonic()
        return [w for w in live if self._full.get(w, (0.0, 0.0))[0] <= now]

    def full_until(self, live: Sequence[str]) -> float:
        """When (``time.monotonic()``) the first of ``live``, all backing off, may take a scene again."""
        return min(self._full[w][0] for w in live)

    def why_full(self, live: Sequence[str]) -> str:
        """Why each of ``live`` backs off, for an error: ``local-0 is full (...); local-1 ...``."""
        return "; ".join(f"{w} {self._full_why.get(w, 'backs off')}" for w in live)

    def lacks(self, slot: int, move: Move, error: RemoteError, live: Sequence[str]) -> None:
        """``move.worker`` has no file for ``move.source`` under its scene roots (``scene_missing``):
        the source is placed on the workers that have it from now on; it leaves the dataset, as a
        source that cannot load does, only when no live worker has it."""
        lacking = self.lacking.setdefault(move.source, set())
        lacking.add(move.worker)
        if set(live) <= lacking:
            self.drop_source(slot, move, error, f"no live worker has it: {sorted(lacking)}")
            return
        log.warning("run %s: worker %s has no %r under its scene roots (%s); that source goes to the other workers "
                    "only. Give every worker of a run the same scene files", self._run_id, move.worker, move.source,
                    error.message)

    def drop_source(self, slot: int, move: Move, error: RemoteError, where: str = "") -> None:
        """A source that cannot load, or whose spawn region has no free position (``scene_error``),
        leaves the dataset; an orphan slot that waited for it takes the next source. The run fails
        only when no source is left."""
        why = f"{error.message} ({where or f'worker {move.worker}'})"
        log.warning("run %s: scene source %r cannot be used (it does not load, or has no room to start in) "
                    "and is dropped from the dataset: %s", self._run_id, move.source, why)
        if not self._dataset.drop(move.source, why):
            raise ConfigError(f"run {self._run_id!r}: no scene source can be loaded: "
                              + "; ".join(f"{src!r}: {w}" for src, w in self._dataset.dropped.items()))
        s = self._table.slots[slot]
        if s.worker is None and s.source == move.source:
            self._table.set_source(slot, self._dataset.next_source())


def _plan_summary(plan: Sequence[tuple[int, Move]]) -> str:
    """``slot 3 on local-0 (swap)``, or per worker and reason ``24 slots (0, 2, 4, ...) on local-0
    (place)``: one short line however many scenes a start-up places."""
    groups: dict[tuple[str, str], list[int]] = {}
    for slot, move in plan:
        groups.setdefault((move.worker, move.reason), []).append(slot)
    return "; ".join(f"{_slot_list(slots)} on {worker} ({reason})" for (worker, reason), slots in groups.items())


def _slot_list(slots: Sequence[int], shown: int = 8) -> str:
    """``slot 3`` or ``12 slots (0, 2, 4, ...)``: one log line however many slots a worker held."""
    slots = [int(s) for s in slots]
    if len(slots) == 1:
        return f"slot {slots[0]}"
    head = ", ".join(map(str, slots[:shown])) + (", ..." if len(slots) > shown else "")
    return f"{len(slots)} slots ({head})"
