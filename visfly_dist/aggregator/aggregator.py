"""The aggregator: poses in, observations out, one round trip per step; scenes kept served.

It ties the parts together: the slot table (:mod:`.slots`, pure placement plans), the worker pool
(:mod:`.pool`, the only I/O), the step plan (:mod:`.step_plan`, which scene entries each worker's
request holds), the assembler (:mod:`.assembler`, replies into buffers, each agent's last good
data), the input checks (:mod:`.inputs`), scene moves
(:mod:`.scene_moves`, loads, switches and unloads in the background) and spawn pools
(:mod:`.spawn_pools`, start positions drawn locally). Workers on this host write their images into
image segments (:mod:`.image_shm`, with shared memory on) instead of the reply.

One step is :meth:`Aggregator.submit` then :meth:`Aggregator.collect`: ``submit`` groups the poses
by worker and sends ONE request per worker (with the spawn poses of agents about to reset, so
their first observation comes in the same round trip) and returns at once; ``collect`` waits for
that ticket's replies and scatters them. Several tickets may be in flight (the async env uses two
groups of agents), and :meth:`wait_any` tells which is ready.

Everything slow happens in the background, never inside a step: scene loads for orphans,
rebalancing and scene swaps are moves (load under a fresh key, switch when the load answered,
unload the old key two collects later, when no request in flight can still name it); spawn pools
are refreshed ahead of use. These requests wait in one list, in the order they were sent, and are
taken in at one place, :meth:`Aggregator._apply_background`, after each collect.

Failure policy (one place, :meth:`_handle_failure`, with what a failed load or spawn request does in
:meth:`_finish_load` and :meth:`_finish_spawn`):
- a worker that dies (liveliness DELETE), misses a deadline or answers ``unknown scene`` (it
  restarted) loses its slots: they become orphans, placed on live workers in the background; the
  agents of a failed request get their last good data and ``lost=True`` (the env truncates them);
- a local worker that missed a deadline is replaced only while other workers are reachable: when
  none is (the router or the network is down), nobody is killed, and the next step waits for
  workers to come back, up to ``PoolConfig.outage_limit_s``, then raises :class:`NoWorkersError`;
- every wait is bounded: a request by ``step_timeout_s``, a load by ``startup_timeout_s``.
"""

from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from visfly_dist.aggregator.assembler import (
    LastGood,
    Observation,
    empty_observation,
    scatter_reply,
)
from visfly_dist.aggregator.config import PoolConfig, SceneSetConfig, new_run_id
from visfly_dist.aggregator.dataset import SceneDataset
from visfly_dist.aggregator.image_shm import ImageSegments, StepImages
from visfly_dist.aggregator.inputs import agent_index, increasing, pose_rows, setting_problems
from visfly_dist.aggregator.pool import BatchTimings, Pending, Reply, WorkerPool
from visfly_dist.aggregator.scene_moves import LoadJob, PendingSwitch, ReconcileJob, SceneMoves, UnloadJob
from visfly_dist.aggregator.slots import SlotTable
from visfly_dist.aggregator.spawn_pools import AgentStreams, PoolKey, SpawnJob, SpawnPools, SpawnSpec, spawn_spec
from visfly_dist.aggregator.step_plan import StepPlans, WorkerEntries, plan_entries
from visfly_dist.errors import AccessDeniedError, ConfigError, ErrorCode, NoWorkersError, RemoteError, VisflyError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.messages import Health, UnloadScene, step_message

log = logging.getLogger(__name__)

CLOSE_UNLOAD_TIMEOUT_S = 2.0
"""How long closing waits for remote workers to unload the run's scenes (an unreachable one is left
to the next run with the run id)."""
_NO_AGENTS = np.zeros(0, np.int64)
_NO_POSES = np.zeros((0, 7))
_NO_ENTRIES = WorkerEntries()

__all__ = ["Aggregator", "Observation", "StepTicket"]


def is_unknown_scene(err: RemoteError) -> bool:
    """The worker does not hold a scene key we sent: it restarted since the scene was loaded."""
    return err.code == ErrorCode.UNKNOWN_SCENE


@dataclass
class _WorkerPart:
    """One worker's share of a ticket: its request, and where its reply rows go."""

    pending: Pending
    slots: list[int]
    obs_rows: np.ndarray     # rows of ticket.obs, in reply order
    spawn_rows: np.ndarray   # rows of ticket.spawn_obs, after those


@dataclass
class StepTicket:
    """A step in flight: what was asked, and the buffers its replies will fill."""

    agents: np.ndarray
    spawn_agents: np.ndarray
    obs: Observation
    spawn_obs: Observation
    parts: list[_WorkerPart]
    started: float
    images: StepImages | None = None  # the segment the workers write this step's images into
    timings: BatchTimings = field(default_factory=BatchTimings)
    collected: bool = False


Job = LoadJob | SpawnJob | UnloadJob | ReconcileJob
"""A request the aggregator does not wait for."""


class Aggregator:
    """The distribution layer between the env and the scene workers (numpy in, numpy out).

    Args:
        pool: where workers come from (see :class:`PoolConfig`).
        scenes: which scenes, how many, how many agents each (see :class:`SceneSetConfig`).
        cameras: the sensors every drone carries.
        drone_radius: collision sphere radius of a drone (m).
        multi_agent: draw the other drones of a scene in each agent's images.
        search_radius: nearest-obstacle search radius (m).
        seed: seed of spawn sampling.

    Every configuration problem raises ConfigError here, before any process starts.
    """

    def __init__(self, pool: PoolConfig, scenes: SceneSetConfig, cameras: Sequence[CameraSpec],
                 drone_radius: float = 0.1, multi_agent: bool = False, search_radius: float = 5.0,
                 seed: int = 0) -> None:
        cameras = tuple(cameras)
        problems = pool.problems() + scenes.problems() + setting_problems(cameras, drone_radius, search_radius)
        if problems:
            raise ConfigError("invalid aggregator configuration: " + "; ".join(problems))
        self.pool_config = pool
        self.scene_config = scenes
        self.cameras = cameras
        self.drone_radius = float(drone_radius)
        self.multi_agent = bool(multi_agent)
        self.search_radius = float(search_radius)
        self.seed = int(seed)
        self.run_id = pool.run_id or new_run_id()
        self.dataset = SceneDataset(scenes.sources, pool.scene_roots, scenes.shuffle, scenes.seed)
        self.agents_per_scene = scenes.agents_per_scene
        self.num_agents = scenes.num_agents
        self.table = SlotTable(self.dataset.take(scenes.num_scenes), self.agents_per_scene)
        self.agent_scene = self.table.agent_scene
        self._last = LastGood(cameras, self.num_agents, self.search_radius)
        self._background: list[Job] = []
        self._plans = StepPlans(self.table)
        self._settled: tuple[int, tuple] | None = None  # (table revision, live generations) of a pass with nothing to do
        self._streams = AgentStreams(self.num_agents)
        self.reseed(self.seed)
        self._pool = WorkerPool(pool, self.run_id)
        self._spawns = SpawnPools(self._pool, self.agents_per_scene, self.seed, pool.step_timeout_s)
        self._moves = SceneMoves(self._pool, self.table, self.dataset, pool, cameras, self.drone_radius,
                                 self.multi_agent, self.run_id)
        self._images = ImageSegments(self.run_id, cameras) if pool.shared_memory else None
        self._started = False
        self._closed = False

    # ----- lifecycle -------------------------------------------------------------------------

    def start(self) -> "Aggregator":
        """Open the session, spawn local workers, wait for them, and load every scene."""
        if self._closed:
            raise ConfigError("this Aggregator was closed; build a new one")
        if self._started:
            return self
        cfg = self.pool_config
        try:
            self._pool.open()
            local = list(self._pool.local_pids())
            live = self._pool.wait_for(cfg.min_workers, cfg.startup_timeout_s, required=local,
                                       remote_may_join=bool(cfg.connect or cfg.listen))
            if len(live) < cfg.min_workers:
                report = self._pool.startup_report()
                user = self._pool.user
                if not live and not report and user:
                    raise AccessDeniedError(
                        f"run {self.run_id!r}: no worker became visible to user {user!r} within startup_timeout_s="
                        f"{cfg.startup_timeout_s}. The router admitted {user!r}, so either no worker joined run "
                        f"{self.run_id!r} (check the workers' --run-id and --connect) or the router's access control "
                        f"denies {user!r} liveliness subscriptions or queries on visfly/{self.run_id}/** (Zenoh drops "
                        "denied messages without telling the client; see deploy/zenoh/router-acl.json5)")
                raise NoWorkersError(
                    f"run {self.run_id!r}: {len(live)} worker(s) came up within startup_timeout_s="
                    f"{cfg.startup_timeout_s}, min_workers={cfg.min_workers} needed"
                    + (f"; {report}" if report else "; check the connect endpoints and the workers' --run-id"))
            self._place_all_now()
            self._started = True
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        """Stop local workers, undeclare, close the session. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            if self._started:
                self._unload_from_remote_workers()
        except VisflyError as exc:  # closing goes on: the next run with this run id unloads them
            log.warning("run %s: unloading the run's scenes from remote workers at close failed: %s", self.run_id, exc)
        finally:
            self._pool.close()
            if self._images is not None:
                self._images.close()

    def _unload_from_remote_workers(self) -> None:
        """Ask the workers this run did not start to drop its scenes (local ones stop with the pool):
        a worker started by hand outlives the run, and would hold them (memory, ``--max-scenes``)
        until the next run with this run id found them. Bounded by :data:`CLOSE_UNLOAD_TIMEOUT_S`."""
        remote = set(self._pool.remote_live_workers())
        targets = [(w, k) for w, k in self._moves.held() if w in remote]
        if not targets:
            return
        replies = self._pool.call([(w, UnloadScene(k).to_message()) for w, k in targets], CLOSE_UNLOAD_TIMEOUT_S)
        left = sorted({r.worker_id for r in replies if r.failure is not None})
        if left:
            log.warning("run %s: could not unload the run's scenes from worker(s) %s at close (%s); the next run "
                        "with this run id unloads them", self.run_id, left, next(r.failure for r in replies if r.failure))

    def __enter__(self) -> "Aggregator":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----- read-only views -------------------------------------------------------------------

    @property
    def workers(self) -> list[str]:
        """Ids of the live workers."""
        return self._pool.live_workers()

    @property
    def num_scenes(self) -> int:
        return len(self.table)

    def assignment(self) -> dict[int, str | None]:
        """Slot index -> id of the worker serving it."""
        return {s.index: s.worker for s in self.table.slots}

    def slot_source(self, slot: int) -> str:
        """The concrete source loaded in ``slot`` (a seeded gen spec or a root-relative path)."""
        return self.table.slots[slot].source

    def agent_bounds(self) -> np.ndarray:
        """``(N, 2, 3)`` float64 flight box of the scene of each agent's running episode."""
        return self.table.agent_bounds()

    def agent_metadata(self, agent: int) -> dict[str, Any]:
        """:meth:`scene_metadata` of the scene agent ``agent``'s running episode is in (while a swap
        takes its slot over, the old or the incoming one)."""
        return self.table.agent_metadata(agent)

    def agent_sources(self) -> list[str]:
        """The source of the scene of each agent's running episode."""
        return self.table.agent_sources()

    def scene_metadata(self, slot: int) -> dict[str, Any]:
        """The metadata the worker reported for ``slot``'s scene, plus its ``source``."""
        meta = dict(self.table.slots[slot].metadata)
        meta.setdefault("source", self.table.slots[slot].source)
        return meta

    def local_worker_pids(self) -> dict[str, int]:
        """Pid of each local worker process (for tests and diagnostics)."""
        return self._pool.local_pids()

    def background_busy(self) -> bool:
        """Whether a scene load, spawn refresh or unload is still in flight (tests, diagnostics)."""
        return bool(self._background)

    def health(self) -> list[dict[str, Any]]:
        """Each live worker's health reply, plus ``local``, ``transport`` (``channel``: a local worker's
        private channel; ``zenoh``) and the ``slots`` it serves."""
        self._require_started()
        live = self._pool.live_workers()
        replies = self._pool.call([(w, Health().to_message()) for w in live], self.pool_config.step_timeout_s)
        out = []
        for reply in replies:
            entry = {k: v for k, v in (reply.message or {}).items() if k not in ("version", "type")}
            entry["worker_id"] = reply.worker_id
            entry["local"] = self._pool.is_local(reply.worker_id)
            entry["transport"] = self._pool.transport(reply.worker_id)
            entry["slots"] = [s.index for s in self.table.slots if s.worker == reply.worker_id]
            if reply.failure is not None or reply.error is not None:
                entry["error"] = reply.failure or str(reply.error)
            out.append(entry)
        return out

    # ----- one step --------------------------------------------------------------------------

    def observe(self, poses: np.ndarray, agents: np.ndarray | None = None, sim_time: float = 0.0) -> Observation:
        """Render every camera and query obstacles for the given agents (submit + collect).

        Args:
            poses: ``(N, 7)`` rows ``[x, y, z, qw, qx, qy, qz]`` of every agent, or ``(k, 7)``
                rows of ``agents`` only.
            agents: indices of the agents to observe (default: all, in order).
            sim_time: simulation time, s (where moving obstacles are), as in :meth:`submit`.
        """
        return self.collect(self.submit(poses, agents, sim_time=sim_time))[0]

    def submit(self, poses: np.ndarray, agents: np.ndarray | None = None, spawn_poses: np.ndarray | None = None,
               spawn_agents: np.ndarray | None = None, sim_time: float = 0.0) -> StepTicket:
        """Send one request per worker for ``agents`` (and the spawn poses of ``spawn_agents``); no wait.

        Args:
            poses: as in :meth:`observe`.
            agents: agents to observe (default all).
            spawn_poses: ``(m, 7)`` poses at which to render ``spawn_agents`` too (their next episode's
                start), in the same requests.
            spawn_agents: ``(m,)`` agent indices (each agent's own scene is used).
            sim_time: simulation time, s, sent with every scene entry: where moving obstacles are drawn
                and queried (0: left off the wire, the workers take 0).
        """
        self._require_started()
        t_start = time.perf_counter()
        agents = self._agents(agents)
        rows = pose_rows(poses, agents, self.num_agents)
        spawn_agents = self._agents(_NO_AGENTS if spawn_agents is None else spawn_agents)
        spawn_rows = pose_rows(_NO_POSES if spawn_poses is None else spawn_poses, spawn_agents, self.num_agents)
        gens = self._maintain()
        obs_plan = self._plans.get(agents)
        spawn_plan = plan_entries(self.table, spawn_agents, next_episode=True) if len(spawn_agents) else {}
        workers = sorted(obs_plan.keys() | spawn_plan.keys())
        generation = [gens[w] if w in gens else self._pool.generation(w) for w in workers]
        segments = self._images
        step = self._step_images(list(zip(workers, generation)), len(agents), spawn_agents, obs_plan.increasing)
        ticket = StepTicket(agents, spawn_agents,
                            empty_observation(self.cameras, len(agents), None if step is None else step.obs),
                            empty_observation(self.cameras, len(spawn_agents), None if step is None else step.spawn), [],
                            t_start, step)
        requests, parts = [], []
        for wid, gen in zip(workers, generation):
            obs, spawn = obs_plan.get(wid, _NO_ENTRIES), spawn_plan.get(wid, _NO_ENTRIES)
            if spawn.keys:
                keys, counts = obs.keys + spawn.keys, np.concatenate((obs.count_array, spawn.count_array))
                poses_w = np.concatenate((rows[obs.rows], spawn_rows[spawn.rows]))
            else:  # the plan's own list and array: nothing is written to a message
                keys, counts, poses_w = obs.keys, obs.count_array, rows[obs.rows]
            times = np.full(len(keys), float(sim_time)) if sim_time else None
            target = None if step is None or segments is None else segments.target(
                step, (wid, gen), obs.start_array, spawn.start_array)
            message = step_message(keys, counts, poses_w, search_radius=self.search_radius, times=times,
                                   image_segment=target)
            requests.append((wid, message))
            parts.append((obs, spawn))
        t0 = time.perf_counter()
        for (obs, spawn), pending in zip(parts, self._pool.send(requests, self.pool_config.step_timeout_s)):
            ticket.parts.append(_WorkerPart(pending, obs.slots, obs.rows, spawn.rows))
        ticket.timings.fanout_s = time.perf_counter() - t0
        ticket.timings.extra["plan_s"] = t0 - t_start
        return ticket

    def _step_images(self, workers: list[tuple[str, int]], obs_rows: int, spawn_agents: np.ndarray,
                     obs_increasing: bool) -> StepImages | None:
        """The image segment of a step to ``workers`` (``(worker, generation)`` pairs), when its rows
        can be laid out in observation order (``obs_increasing``: the agents are in increasing order,
        as the env always asks; the spawn agents too): then each entry's rows are one run."""
        if self._images is None or not workers or not (obs_increasing and increasing(spawn_agents)):
            return None
        return self._images.offer(workers, obs_rows, len(spawn_agents))

    def ready(self, ticket: StepTicket) -> bool:
        """Whether every reply of ``ticket`` is in (``collect`` will not wait)."""
        return all(p.pending.done() for p in ticket.parts)

    def wait_any(self, tickets: Sequence[StepTicket], timeout_s: float | None = None) -> int | None:
        """Index of the first of ``tickets`` whose replies are all in (``None`` on timeout)."""
        timeout = self.pool_config.step_timeout_s + 5.0 if timeout_s is None else timeout_s
        return self._pool.wait_any([[p.pending for p in t.parts] for t in tickets], timeout)

    def collect(self, ticket: StepTicket) -> tuple[Observation, Observation]:
        """Wait for ``ticket``'s replies; the observation of its agents and of its spawn poses.

        Agents whose worker failed get their last good data and ``lost=True``; spawn rows that
        could not be rendered have ``lost=True`` (the env renders those again when it needs them).
        ``obs.timings``: ``fanout_s``, ``wait_s``, ``decode_s``, ``assemble_s``, the slowest worker's
        own stages (``render_s``, ``query_s``, ...), ``transport_s`` (fan-out and wait minus the
        slowest worker's total) and ``total_s`` (submit to collect).
        """
        if ticket.collected:
            raise ConfigError("this ticket was already collected")
        ticket.collected = True
        replies = self._pool.gather([p.pending for p in ticket.parts], ticket.timings)
        t0 = time.perf_counter()
        worker_timings = []
        segments, step, failed = self._images, ticket.images, False
        for part, reply in zip(ticket.parts, replies):
            in_place = False
            if segments is not None and step is not None and reply.message is not None:
                in_place, problem = segments.check(step, reply.worker_id, reply.message)
                if problem:
                    reply = Reply(reply.worker_id, failure=problem)
            if reply.message is None:
                failed = True
                self._handle_failure(reply, part.slots)
                continue
            message = reply.message
            timings = message.get("timings")
            if isinstance(timings, dict):
                worker_timings.append(timings)  # read only: the decoded reply's own map
            scatter_reply(ticket.obs, part.obs_rows, ticket.spawn_obs, part.spawn_rows, message, self.cameras,
                          reply.worker_id, in_place)
        if segments is not None and step is not None:
            self._release_images(ticket, segments, step, failed)
        if ticket.obs.lost.any():
            stale = np.flatnonzero(ticket.obs.lost)
            self._last.fill(ticket.obs, stale, ticket.agents[stale])
            fresh = np.flatnonzero(~ticket.obs.lost)
            self._last.remember(ticket.obs, fresh, ticket.agents[fresh])
        else:
            self._last.remember(ticket.obs, np.arange(len(ticket.agents)), ticket.agents)
        assemble_s = time.perf_counter() - t0
        self._moves.note_collect()
        self._apply_background()
        ticket.obs.timings = ticket.timings.step_report(worker_timings, assemble_s, time.perf_counter() - ticket.started)
        return ticket.obs, ticket.spawn_obs

    def hold_observations(self, count: int) -> None:
        """The caller keeps up to ``count`` observations at once: the image segments they are views of
        are offered again once let go, not replaced by new ones (:meth:`ImageSegments.hold`)."""
        if self._images is not None:
            self._images.hold(count)

    def _release_images(self, ticket: StepTicket, segments: ImageSegments, step: StepImages, failed: bool) -> None:
        """Done with the step's segment. After a failed request the images are copied out (the late
        worker may still write there); rows written over after their reply was read are lost."""
        over = segments.release(step, failed)
        if failed or over:
            ticket.obs = ticket.obs.take(np.arange(len(ticket.agents)))
            ticket.spawn_obs = ticket.spawn_obs.take(np.arange(len(ticket.spawn_agents)))
        for part in ticket.parts:
            if part.pending.worker_id in over:
                ticket.obs.lost[part.obs_rows] = True
                ticket.spawn_obs.lost[part.spawn_rows] = True
                self._handle_failure(Reply(part.pending.worker_id, failure=(
                    f"image segment {step.segment.name} was written over after its images were read")), part.slots)

    # ----- spawn draws -----------------------------------------------------------------------

    def sample_spawn(self, agents: np.ndarray, distribution: str, a: Sequence[float], b: Sequence[float],
                     clearance: float) -> np.ndarray:
        """Free positions for ``agents``, ``(k, 3)`` float64, drawn locally from per-scene pools.

        Each (scene, distribution) pool of ``max(256, 8 * agents_per_scene)`` positions is sampled
        by the scene's worker. Each agent draws from its own stream (:meth:`reseed`), so its starts
        do not depend on the other agents' resets. A pool is refreshed
        with fresh samples in the background once half of it has been drawn, and replaced when
        all of it has (at a draw count, not a time, so the same seed gives the same positions).
        Only the very first draw from a scene waits for its pool.
        """
        self._require_started()
        agents = self._agents(agents)
        spec = spawn_spec(distribution, a, b, clearance)
        out = np.empty((len(agents), 3), dtype=np.float64)
        if not len(agents):
            return out
        # the agents grouped by slot once: each group's rows, in increasing order, are a run of ``order``
        slot_of = self.agent_scene[agents]
        order = np.argsort(slot_of, kind="stable")
        slot_sorted = slot_of[order]
        cuts = (np.flatnonzero(slot_sorted[1:] != slot_sorted[:-1]) + 1).tolist()
        starts, ends, slots = [0, *cuts], [*cuts, len(agents)], slot_sorted[[0, *cuts]].tolist()
        missing = [s for s in slots if self._pool_key(s, spec) not in self._spawns]  # each agent's next episode
        if missing:  # starts in its slot's next scene (an armed swap's)
            self._fetch_spawn_pools_now(missing, spec)
        draws = self._streams.draw(agents)[order]
        picked = []
        for slot, start, end in zip(slots, starts, ends):
            key = self._pool_key(slot, spec)  # here, not before: a refresh waited for may arm a swap
            positions, half_drawn = self._spawns.draw(key, draws[start:end])
            picked.append(positions)
            if half_drawn:
                self._keep_fresh(key)
        out[order] = picked[0] if len(picked) == 1 else np.concatenate(picked)
        return out

    def reseed(self, seeds: int | Sequence[int], agents: np.ndarray | None = None) -> None:
        """Restart the spawn draws of ``agents`` (default: all): agent ``agents[i]`` draws from
        ``seeds[i]``; an int ``seed`` gives agent ``a`` the seed ``seed + a`` (as Gymnasium and SB3 seed
        sub-envs). The per-scene pools stay as they are."""
        self._streams.reseed(self._agents(agents), seeds)

    def _pool_key(self, slot: int, spec: SpawnSpec) -> PoolKey:
        """The pool that next episodes in ``slot`` start from: its armed swap's scene, else its own."""
        return PoolKey(slot, self._next_scene(slot)[2], spec)

    def _next_scene(self, slot: int) -> tuple[str | None, str, str]:
        """``(worker, key, source)`` of the scene next episodes in ``slot`` start in."""
        s = self.table.slots[slot]
        if s.incoming is not None:
            return s.incoming.move.worker, s.incoming.move.key, s.incoming.move.source
        return s.worker, s.key, s.source

    def _keep_fresh(self, key: PoolKey) -> None:
        """Ask for a pool's refresh at half its size; swap it in once the whole pool was drawn
        (called once half of it was drawn: before, neither is due)."""
        in_flight = [j.pending for j in self._background if isinstance(j, SpawnJob) and j.key == key]
        worker, scene_key, _ = self._next_scene(key.slot)
        if self._spawns.wants_refresh(key, bool(in_flight)) and worker is not None:
            self._background.append(self._spawns.fetch(key, worker, scene_key, refresh=True))
        elif self._spawns.used_up(key):
            if in_flight:  # bounded wait, so the same seed gives the same positions
                self._pool.wait_any([in_flight], self.pool_config.step_timeout_s)
                self._apply_background()
            self._spawns.replace(key)

    def _fetch_spawn_pools_now(self, slots: list[int], spec: SpawnSpec) -> None:
        """Blocking first fetch of the pools of ``slots`` (at reset, before any step uses them)."""
        for _ in range(3):
            scenes = {s: self._next_scene(s) for s in slots}
            jobs = [self._spawns.fetch(self._pool_key(s, spec), worker, key)
                    for s, (worker, key, _) in scenes.items() if worker is not None]
            self._background.extend(jobs)
            self._pool.gather([j.pending for j in jobs])
            self._apply_background()
            slots = [s for s in slots if self._pool_key(s, spec) not in self._spawns]
            if not slots:
                return
            self._place_all_now()
        raise NoWorkersError(f"run {self.run_id!r}: no worker could sample spawn positions for slots {slots}")

    # ----- scene swaps -----------------------------------------------------------------------

    def note_resets(self, agents: np.ndarray, count: bool = True) -> np.ndarray:
        """Agents ``agents`` start new episodes (call before they start): with ``count`` (their
        episodes ended; not for a reset asked for), count resets per slot and start loading the next
        scene of slots due for a swap. Returns the agents whose new episode is in a swapped-in scene
        (their bounds and metadata changed).

        A swap loads in the background; once its scene and spawn pools are ready it is armed
        (:meth:`take_next_scene` reports the agents whose next start must be drawn there) and each
        agent moves into it at its next episode end: no running episode changes scene.
        """
        self._require_started()
        agents = self._agents(agents)
        moved = self._moves.take_over(agents)
        every = self.scene_config.swap_every_resets
        if every == 0 or len(agents) == 0 or not count:
            return moved
        counts = np.bincount(self.agent_scene[agents], minlength=len(self.table))
        self._background.extend(self._moves.start_swaps(counts, every, self._swap_workers))
        return moved

    def _swap_workers(self) -> tuple[dict[str, int], dict[str, int]]:
        """The live workers' generations and the scene loads each has in flight (for swaps)."""
        loading = collections.Counter(j.move.worker for j in self._background if isinstance(j, LoadJob))
        return self._pool.generations(self._pool.live_workers()), loading

    def take_next_scene(self) -> np.ndarray:
        """``(N,)`` bool: agents whose next episode starts in a newly armed swap (draw their next
        start again) since the last call."""
        return self._moves.take_next_scene()

    def take_switched(self) -> np.ndarray:
        """``(N,)`` bool: agents whose scene changed under their running episode since the last call
        (a worker lost while its slot's agents were taking a swap over; the env cuts those episodes)."""
        return self._moves.take_switched()

    # ----- failure policy --------------------------------------------------------------------

    def _handle_failure(self, reply: Reply, slots: Sequence[int] = ()) -> None:
        """The one failure policy: what a failed or refused request does to its worker and slots."""
        if reply.error is not None and not is_unknown_scene(reply.error):
            raise reply.error
        if reply.error is not None:  # restarted under the same id: its scenes are gone, the worker is fine
            reason = f"forgot its scenes ({reply.error.message})"
        else:
            reason = reply.failure or "failed"
            if not self._pool.dropped(reply.worker_id):  # once dropped, the requests it left unanswered change nothing
                # Replaced while others answer: when none does, the router or the network may be down and the
                # worker fine. A local worker on its private channel has no network in between: replaced anyway.
                others = [w for w in self._pool.live_workers() if w != reply.worker_id]
                replace = bool(others) or self._pool.transport(reply.worker_id) == "channel"
                self._pool.drop(reply.worker_id, reason, replace=replace, unanswered_bytes=reply.unanswered_bytes)
        self._moves.orphan(reply.worker_id, reason)

    def _maintain(self) -> dict[str, int]:
        """Orphan slots of dead or restarted workers; start loads for orphans; rebalance; wait out
        outages. Returns the generation of each live worker."""
        self._pool.respawn_exited()
        self._pool.recheck_banned()
        live = self._pool.live_workers()
        gens = self._pool.generations(live)
        self._background.extend(self._moves.reconcile(gens))
        settled = (self.table.revision, tuple(gens.items()))
        if settled == self._settled and not (self._background or self._moves.stale or self._moves.switching):
            return gens  # nothing changed since a pass that found nothing to do: it would find nothing again
        for s in self.table.slots:
            if s.worker is not None and (s.worker not in gens or gens[s.worker] != s.generation):
                why = "liveliness token gone" if s.worker not in gens else "restarted"
                self._moves.orphan(s.worker, why)
        self._send_unloads(self._moves.take_stale(live))
        if not live:
            live = self._wait_out_outage()
            gens = self._pool.generations(live)
        placeable = self._moves.placeable(live)
        plan = self.table.plan_placement(placeable, gens, self._moves.lacking)
        if not plan and not self.table.orphans():
            # also while loads run (navigation's swaps keep some running): a move in flight counts on
            # its target and its slot is not moved again, so a rejoining worker gets its share now
            plan = self.table.plan_rebalance(placeable, gens, self._moves.lacking)
        self._background.extend(self._moves.send_loads(plan))
        busy = plan or self._background or self._moves.switching or len(placeable) < len(live)
        self._settled = None if busy else (self.table.revision, tuple(gens.items()))
        return gens

    def _wait_out_outage(self) -> list[str]:
        """No worker is reachable: wait for one (up to ``outage_limit_s``), or raise NoWorkersError."""
        limit = self.pool_config.outage_limit_s
        log.warning("run %s: no scene worker reachable; waiting up to %g s", self.run_id, limit)
        live = self._pool.wait_for(1, limit, remote_may_join=True)
        if not live:
            where = f"router/endpoints {list(self.pool_config.connect)}" if self.pool_config.connect else "local workers"
            raise NoWorkersError(
                f"run {self.run_id!r}: no scene worker reachable for outage_limit_s={limit:g} s ({where}); "
                "the router or the network is unreachable, or every worker is gone"
                + (f"; {self._pool.startup_report()}" if self._pool.startup_report() else ""))
        return live

    def _place_all_now(self) -> None:
        """Load every orphan and wait for the loads (start-up, and the rare blocking fallback), for up
        to ``startup_timeout_s`` while every worker is full."""
        deadline = time.monotonic() + self.pool_config.startup_timeout_s
        for _ in range(len(self.table) + 64):
            if not self.table.orphans():
                return
            live = self._pool.require_live()
            placeable = self._moves.placeable(live)
            if not placeable:  # every worker is full for now: wait for the first backoff to end
                until = self._moves.full_until(live)
                if until > deadline:
                    raise NoWorkersError(
                        f"run {self.run_id!r}: {len(self.table.orphans())} scene slot(s) could not be placed within "
                        f"startup_timeout_s={self.pool_config.startup_timeout_s:g}: every live worker backs off "
                        f"({self._moves.why_full(live)}). Start more workers, raise their memory bound "
                        "(--max-memory-mb), or load fewer scene copies (fewer envs, or more agents_per_scene)")
                time.sleep(max(0.0, until - time.monotonic()))
                continue
            gens = self._pool.generations(live)
            self._background.extend(self._moves.send_loads(self.table.plan_placement(placeable, gens, self._moves.lacking)))
            jobs = [j for j in self._background if isinstance(j, LoadJob)]
            self._pool.gather([j.pending for j in jobs])
            self._apply_background()
        raise NoWorkersError(f"run {self.run_id!r}: could not place scenes after repeated worker failures")

    # ----- background requests, taken in at one place ----------------------------------------

    def _apply_background(self) -> None:
        """Take in every finished background request, in the order they were sent; send the unloads due."""
        self._send_unloads(self._moves.due_unloads())
        still: list[Job] = []
        for job in self._background:
            if not job.pending.done():
                still.append(job)
                continue
            reply = self._pool.result(job.pending)
            if isinstance(job, LoadJob):
                self._finish_load(job, reply, still)
            elif isinstance(job, SpawnJob):
                self._finish_spawn(job, reply)
            elif isinstance(job, ReconcileJob):
                unloading = {j.key for j in self._background if isinstance(j, UnloadJob) and j.worker == job.worker}
                self._send_unloads(self._moves.finish_reconcile(job, reply, unloading))
            else:
                self._moves.finish_unload(job, reply)
        self._background = still

    def _finish_load(self, job: LoadJob, reply: Reply, still: list[Job]) -> None:
        """A load answered: its slot switches (a swap once the new scene's spawn pools are in). What
        a failed load does depends on why it failed."""
        move = job.move
        if reply.message is None:
            self.table.fail_move(job.slot, move)
            if reply.error is not None and reply.error.code == ErrorCode.SCENE_ERROR:
                self._moves.drop_source(job.slot, move, reply.error)
                return
            if reply.error is not None and reply.error.code == ErrorCode.SCENE_MISSING:
                self._moves.lacks(job.slot, move, reply.error, self._pool.live_workers())
                return
            if reply.error is not None and reply.error.code == ErrorCode.OVERLOADED:
                self._moves.back_off(move.worker, f"is full ({reply.error.message})")
                return
            if reply.error is not None and not is_unknown_scene(reply.error):
                raise RemoteError(move.worker, reply.error.error_type,
                                  f"loading {move.source!r} into slot {job.slot}: {reply.error.message}")
            if reply.failure is not None:  # the load may still end on the worker: unload it when it is back
                self._moves.mark_stale(move.worker, move.key)
            if reply.unanswered_bytes and move.worker in self._pool.live_workers() and self._pool.probe(move.worker):
                # alive and answering: its loads are slower than they were asked for (a loaded host),
                # not lost; its slots keep serving and it gets no new scene for a while
                self._moves.back_off(move.worker, f"did not finish loading {move.source!r} in time ({reply.failure})")
                return
            self._handle_failure(reply)
            return
        if self.table.slots[job.slot].move is not move:  # cancelled (its worker failed meanwhile): not used
            self._moves.mark_stale(move.worker, move.key)
            return
        bounds, metadata = reply.message["bounds"], reply.message.get("metadata", {})
        specs = self._spawns.specs_of(job.slot)
        if move.reason == "swap" and specs:
            # The new scene's spawn pools come first, so resets never wait for them.
            self._moves.await_pools(job.slot, PendingSwitch(move, bounds, metadata, set(specs)))
            still.extend(self._spawns.fetch(PoolKey(job.slot, move.source, spec), move.worker, move.key) for spec in specs)
            return
        self._moves.switch(job.slot, move, bounds, metadata)

    def _finish_spawn(self, job: SpawnJob, reply: Reply) -> None:
        """A pool arrived (a swap waiting for it may switch now), or the failure policy for its request."""
        if reply.message is None:
            swap = self._moves.cancel_switch(job.key.slot)  # a swap's scene that is loaded but will not be used
            error = reply.error
            if error is not None and error.code == ErrorCode.SCENE_ERROR and swap is not None \
                    and swap.source == job.key.source:  # no room to start in it: the swap's source leaves the dataset
                self._moves.drop_source(job.key.slot, swap, error)
                return
            if error is not None and not is_unknown_scene(error):
                raise RemoteError(reply.worker_id, error.error_type, f"sampling spawn positions in {job.key.source!r} "
                                  f"(slot {job.key.slot}): {error.message}", code=error.code)
            self._handle_failure(reply)
            return
        positions = np.asarray(reply.message["positions"], dtype=np.float64).reshape(-1, 3)
        if len(positions) == 0:
            raise RemoteError(reply.worker_id, "SceneError",
                              f"no free spawn position in {job.key.source!r} for {tuple(job.key.spec)}")
        self._spawns.store(job, positions)
        if not job.refresh:
            self._moves.pool_ready(job.key)

    def _send_unloads(self, targets: Sequence[tuple[str, str]]) -> None:
        """Unload each ``(worker, key)`` in the background (:meth:`SceneMoves.send_unloads`)."""
        self._background.extend(self._moves.send_unloads(targets))

    # ----- input checks ----------------------------------------------------------------------

    def _require_started(self) -> None:
        if not self._started or self._closed:
            raise ConfigError("call Aggregator.start() (or use it as a context manager) before this; "
                              + ("it was closed" if self._closed else "it was not started"))

    def _agents(self, agents: np.ndarray | Sequence[int] | None) -> np.ndarray:
        return agent_index(agents, self.num_agents)
