"""The aggregator: scenes in slots on workers, one fan-out per observation, and failure recovery.

Agents are grouped in slots: agent ``i`` flies in slot ``i // agents_per_scene``. Each slot holds
one scene (a concrete source) loaded on one worker under the key ``s<slot>``. The env owns the
dynamics; the aggregator turns poses into observations and keeps the slots served.

Failure invariants (the core of this module):
- A slot is served by a worker only while that worker is live (liveliness token present, not
  banned) at the generation the scene was loaded at. Anything else makes the slot an orphan.
- A worker that dies (token DELETE), misses a deadline (no reply, ``Timeout``) or restarted
  (new generation) is dropped; every slot it held becomes an orphan at once, and the agents of
  those slots are marked *pending lost*.
- Orphans are placed on the least-loaded live workers (LoadScene, all in flight). With no live
  worker, a respawned local one is waited for (``startup_timeout_s``); with none possible,
  NoWorkersError. Placement repeats until no orphan is left, each round dropping the workers that
  failed to load, so it ends: every round either places all orphans or drops a worker.
- ``observe`` reports ``lost=True`` exactly for the requested agents that were pending lost, then
  clears them: each agent whose scene moved is reported lost once. Lost agents get fresh data from
  the new worker within the same call if the call is still under ``step_timeout_s``, else their
  last good data (zeros and ``far`` depth if none).
- No wait is unbounded: every request carries a timeout; a call makes at most a bounded number of
  rounds (the initial batch, placement rounds bounded by the number of workers, one refetch).
- A worker's error reply is a bug (RemoteError), except an unknown scene key (the worker
  restarted between our liveliness check and the request): reload there and retry once.
"""

from __future__ import annotations

import logging
import time
import zlib
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from visfly_dist.aggregator.config import PoolConfig, SceneSetConfig, new_run_id
from visfly_dist.aggregator.dataset import SceneDataset
from visfly_dist.aggregator.pool import BatchTimings, Reply, WorkerPool
from visfly_dist.errors import AccessDeniedError, ConfigError, NoWorkersError, ProtocolError, RemoteError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.messages import Health, LoadScene, SampleSpawn, ScenePoses, StepRequest, UnloadScene

log = logging.getLogger(__name__)

SPAWN_POOL_MIN = 256


@dataclass
class Observation:
    """What the workers saw for ``k`` agents, in the order they were asked for.

    Attributes:
        images: camera name -> ``(k, C, H, W)`` array of the camera's dtype.
        collision: ``(k,)`` bool, the drone's sphere touches an obstacle.
        inside: ``(k,)`` bool, the drone is inside a closed obstacle.
        nearest: ``(k, 3)`` float32 nearest obstacle point (world, m).
        distance: ``(k,)`` float32 distance to it (m), capped at the search radius.
        lost: ``(k,)`` bool, the agent's scene moved to another worker (its worker failed): the
            env truncates these agents. Their data is fresh if it could be re-fetched in time,
            else the last good one.
        timings: seconds per stage: ``fanout_s``, ``wait_s``, ``decode_s``, ``assemble_s``,
            the slowest worker's own stages (e.g. ``render_s``, ``query_s``), ``transport_s``
            (fan-out and wait minus the slowest worker's total), ``recovery_s`` when any, and ``total_s``.
    """

    images: dict[str, np.ndarray]
    collision: np.ndarray
    inside: np.ndarray
    nearest: np.ndarray
    distance: np.ndarray
    lost: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class _Slot:
    """One scene slot; ``worker`` is ``None`` while it is an orphan."""

    index: int
    source: str
    worker: str | None = None
    generation: int = 0
    bounds: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    metadata: dict[str, Any] = field(default_factory=dict)
    resets: int = 0

    @property
    def key(self) -> str:
        return f"s{self.index}"


def _is_unknown_scene(err: RemoteError) -> bool:
    """The worker does not hold a scene key we sent (it restarted): the worker's SceneTable wording."""
    return err.error_type == "SceneError" and "is not loaded on this worker" in err.message


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
        problems = pool.problems() + scenes.problems()
        cameras = tuple(cameras)
        if not cameras or not all(isinstance(c, CameraSpec) for c in cameras):
            problems.append(f"cameras={cameras!r} must be a non-empty sequence of CameraSpec")
        elif len({c.name for c in cameras}) != len(cameras):
            problems.append(f"camera names {[c.name for c in cameras]} must be unique")
        if not 0 <= float(drone_radius) <= 10:
            problems.append(f"drone_radius={drone_radius!r} must be in [0, 10] m")
        if not 0 < float(search_radius) <= 1e4:
            problems.append(f"search_radius={search_radius!r} must be in (0, 1e4] m")
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

        aps = scenes.agents_per_scene
        self.agents_per_scene = aps
        self.num_agents = scenes.num_agents
        self.agent_scene = np.arange(self.num_agents, dtype=np.int64) // aps
        self._slots = [_Slot(i, source) for i, source in enumerate(self.dataset.take(scenes.num_scenes))]
        self._pending_lost = np.zeros(self.num_agents, dtype=bool)
        self._last = self._blank(self.num_agents)
        self._spawn_pools: dict[tuple, np.ndarray] = {}
        self._rng = np.random.default_rng(self.seed)
        self._pool = WorkerPool(pool, self.run_id)
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
            self._place_orphans()
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
        self._pool.close()

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
        return len(self._slots)

    def assignment(self) -> dict[int, str | None]:
        """Slot index -> id of the worker serving it."""
        return {s.index: s.worker for s in self._slots}

    def slot_source(self, slot: int) -> str:
        """The concrete source loaded in ``slot`` (a seeded gen spec or a root-relative path)."""
        return self._slots[slot].source

    def agent_bounds(self) -> np.ndarray:
        """``(N, 2, 3)`` float64 flight box of each agent's scene."""
        return np.stack([self._slots[s].bounds for s in self.agent_scene]).astype(np.float64)

    def scene_metadata(self, slot: int) -> dict[str, Any]:
        """The metadata the worker reported for ``slot``'s scene, plus its ``source``."""
        meta = dict(self._slots[slot].metadata)
        meta.setdefault("source", self._slots[slot].source)
        return meta

    def local_worker_pids(self) -> dict[str, int]:
        """Pid of each local worker process (for tests and diagnostics)."""
        return self._pool.local_pids()

    # ----- observe ---------------------------------------------------------------------------

    def observe(self, poses: np.ndarray, agents: np.ndarray | None = None) -> Observation:
        """Render every camera and query obstacles for the given agents.

        Args:
            poses: ``(N, 7)`` rows ``[x, y, z, qw, qx, qy, qz]`` of every agent, or ``(k, 7)``
                rows of ``agents`` only.
            agents: indices of the agents to observe (default: all, in order).

        Returns:
            The observation of ``agents``, in their order.
        """
        self._require_started()
        t_start = time.perf_counter()
        agents = self._agent_index(agents)
        rows = self._pose_rows(poses, agents)
        timings = BatchTimings()
        t0 = time.perf_counter()
        self._maintain()
        recovery_s = time.perf_counter() - t0

        positions: dict[int, np.ndarray] = {}  # slot -> positions in `agents`
        for slot in np.unique(self.agent_scene[agents]):
            positions[int(slot)] = np.flatnonzero(self.agent_scene[agents] == slot)
        results, worker_timings = self._step_slots(list(positions), positions, rows, timings)

        refetch = [s for s in positions if s not in results]
        if refetch:
            t0 = time.perf_counter()
            self._place_orphans()
            if time.perf_counter() - t_start < self.pool_config.step_timeout_s:
                more, more_timings = self._step_slots(refetch, positions, rows, timings, retry_unknown=False)
                results.update(more)
                worker_timings += more_timings
            recovery_s += time.perf_counter() - t0

        t0 = time.perf_counter()
        obs = self._assemble(agents, rows, positions, results)
        assemble_s = time.perf_counter() - t0
        obs.timings = self._timings(timings, worker_timings, assemble_s, recovery_s, time.perf_counter() - t_start)
        return obs

    def _step_slots(self, slots: list[int], positions: dict[int, np.ndarray], rows: np.ndarray,
                    timings: BatchTimings, retry_unknown: bool = True) -> tuple[dict[int, dict], list[dict]]:
        """One StepRequest per worker covering ``slots``; returns per-slot results and worker timings.

        Slots of failing workers get no result (those workers are dropped, their slots orphaned).
        """
        by_worker: dict[str, list[int]] = {}
        for s in slots:
            if self._slots[s].worker is not None:
                by_worker.setdefault(self._slots[s].worker, []).append(s)
        requests = []
        for wid in sorted(by_worker):
            scenes = tuple(ScenePoses(self._slots[s].key, rows[positions[s]]) for s in by_worker[wid])
            requests.append((wid, StepRequest(scenes, search_radius=self.search_radius).to_message()))
        replies = self._pool.call(requests, self.pool_config.step_timeout_s, timings)
        results: dict[int, dict] = {}
        worker_timings: list[dict] = []
        redo: list[int] = []
        for reply in replies:
            if reply.failure is not None:
                self._orphan_worker_slots(reply.worker_id, drop=True, reason=reply.failure)
            elif reply.error is not None:
                if not (retry_unknown and _is_unknown_scene(reply.error)):
                    raise reply.error
                # The worker restarted under the same id since we loaded: reload, retry once.
                self._orphan_worker_slots(reply.worker_id, drop=False, reason=f"forgot its scenes ({reply.error})")
                redo += by_worker[reply.worker_id]
            else:
                worker_timings.append(dict(reply.message.get("timings", {})))
                got = {scene.get("scene_key"): scene for scene in reply.message.get("scenes", [])}
                for s in by_worker[reply.worker_id]:
                    results[s] = self._checked(reply.worker_id, got.get(self._slots[s].key), s, len(positions[s]))
        if redo:
            self._place_orphans()
            more, more_timings = self._step_slots(redo, positions, rows, timings, retry_unknown=False)
            results.update(more)
            worker_timings += more_timings
        return results, worker_timings

    def _checked(self, wid: str, scene: dict | None, slot: int, n: int) -> dict:
        """A worker's result for one slot, checked against what was asked (ProtocolError if not)."""
        if scene is None:
            raise ProtocolError(f"worker {wid!r} sent no result for scene key {self._slots[slot].key!r}")
        images = scene.get("images") or {}
        arrays = [(cam.name, images.get(cam.name), (n, *cam.shape)) for cam in self.cameras]
        arrays += [(key, scene.get(key), shape) for key, shape in
                   (("collision", (n,)), ("inside", (n,)), ("nearest", (n, 3)), ("distance", (n,)))]
        for name, value, shape in arrays:
            if not isinstance(value, np.ndarray) or value.shape != shape:
                got = getattr(value, "shape", type(value).__name__)
                raise ProtocolError(f"worker {wid!r} sent {name} of shape {got} for slot {slot}; expected {shape}")
        return scene

    def _assemble(self, agents: np.ndarray, rows: np.ndarray, positions: dict[int, np.ndarray],
                  results: dict[int, dict]) -> Observation:
        k = len(agents)
        out = self._blank(k)
        for slot, pos in positions.items():
            idx = agents[pos]
            res = results.get(slot)
            if res is None:  # last good data of these agents
                for name in out["images"]:
                    out["images"][name][pos] = self._last["images"][name][idx]
                for key in ("collision", "inside", "nearest", "distance"):
                    out[key][pos] = self._last[key][idx]
                continue
            for cam in self.cameras:
                img = res["images"][cam.name]
                out["images"][cam.name][pos] = img
                self._last["images"][cam.name][idx] = img
            for key in ("collision", "inside", "nearest", "distance"):
                out[key][pos] = res[key]
                self._last[key][idx] = res[key]
        lost = self._pending_lost[agents].copy()
        self._pending_lost[agents] = False
        return Observation(out["images"], out["collision"], out["inside"], out["nearest"], out["distance"], lost)

    def _blank(self, n: int) -> dict[str, Any]:
        """Arrays for ``n`` agents holding "nothing seen": far depth, no obstacle within reach."""
        images = {}
        for cam in self.cameras:
            fill = cam.far if cam.kind == "depth" else 0
            images[cam.name] = np.full((n, *cam.shape), fill, dtype=cam.dtype)
        return {"images": images, "collision": np.zeros(n, bool), "inside": np.zeros(n, bool),
                "nearest": np.zeros((n, 3), np.float32), "distance": np.full(n, self.search_radius, np.float32)}

    @staticmethod
    def _timings(batch: BatchTimings, workers: list[dict], assemble_s: float, recovery_s: float,
                 total_s: float) -> dict[str, float]:
        out = {"fanout_s": batch.fanout_s, "wait_s": batch.wait_s, "decode_s": batch.decode_s,
               "assemble_s": assemble_s}
        own = set(out)
        worker_total = 0.0
        for wt in workers:
            stages = {k: float(v) for k, v in wt.items() if isinstance(v, (int, float)) and k != "total_s"}
            for stage, seconds in stages.items():
                name = f"worker_{stage}" if stage in own else stage  # the worker's decode_s is not ours
                out[name] = max(out.get(name, 0.0), seconds)
            worker_total = max(worker_total, float(wt.get("total_s", sum(stages.values()))))
        out["worker_total_s"] = worker_total
        out["transport_s"] = max(0.0, batch.fanout_s + batch.wait_s - worker_total)
        if recovery_s > 1e-3:
            out["recovery_s"] = recovery_s
        out["total_s"] = total_s
        return out

    # ----- spawn sampling --------------------------------------------------------------------

    def sample_spawn(self, agents: np.ndarray, distribution: str, a: Sequence[float], b: Sequence[float],
                     clearance: float) -> np.ndarray:
        """Free positions for ``agents``, ``(k, 3)`` float64, drawn from per-scene pools.

        Each (scene, distribution) pool of ``max(256, 8 * agents_per_scene)`` positions is sampled
        once by the scene's worker; draws from it use this aggregator's seeded generator, so the
        same seed gives the same positions.

        Args:
            agents: agent indices.
            distribution: ``"uniform"`` (``a`` low corner, ``b`` high corner) or ``"normal"``
                (``a`` mean, ``b`` std).
            a: 3 numbers.
            b: 3 numbers.
            clearance: minimum distance to any obstacle (m).
        """
        self._require_started()
        agents = self._agent_index(agents)
        spec = self._spawn_spec(distribution, a, b, clearance)
        slots = sorted({int(s) for s in self.agent_scene[agents]})
        self._maintain()
        for _ in range(2):
            missing = [s for s in slots if (s, self._slots[s].source, spec) not in self._spawn_pools]
            if not missing:
                break
            self._fetch_spawn_pools(missing, spec)
            self._place_orphans()
        missing = [s for s in slots if (s, self._slots[s].source, spec) not in self._spawn_pools]
        if missing:
            raise NoWorkersError(f"run {self.run_id!r}: no worker could sample spawn positions for slots {missing}")
        draws = self._rng.integers(0, 2**31 - 1, size=len(agents))
        out = np.empty((len(agents), 3), dtype=np.float64)
        for i, (agent, draw) in enumerate(zip(agents, draws)):
            slot = int(self.agent_scene[agent])
            pool = self._spawn_pools[(slot, self._slots[slot].source, spec)]
            out[i] = pool[draw % len(pool)]
        return out

    def reseed(self, seed: int) -> None:
        """Restart the spawn draws from ``seed`` (the per-scene pools stay as they are)."""
        self._rng = np.random.default_rng(int(seed))

    @staticmethod
    def _spawn_spec(distribution: str, a: Sequence[float], b: Sequence[float], clearance: float) -> tuple:
        problems = []
        if distribution not in ("uniform", "normal"):
            problems.append(f"distribution={distribution!r} must be 'uniform' or 'normal'")
        va, vb = np.asarray(a, dtype=np.float64).ravel(), np.asarray(b, dtype=np.float64).ravel()
        if va.shape != (3,) or vb.shape != (3,) or not (np.all(np.isfinite(va)) and np.all(np.isfinite(vb))):
            problems.append(f"a={a!r} and b={b!r} must be 3 finite numbers each")
        elif distribution == "uniform" and np.any(va > vb):
            problems.append(f"uniform low a={list(va)} must not exceed high b={list(vb)}")
        elif distribution == "normal" and np.any(vb < 0):
            problems.append(f"normal std b={list(vb)} must be non-negative")
        if not 0 <= float(clearance) <= 100:
            problems.append(f"clearance={clearance!r} must be in [0, 100] m")
        if problems:
            raise ConfigError("invalid spawn request: " + "; ".join(problems))
        return (distribution, tuple(va.tolist()), tuple(vb.tolist()), float(clearance))

    def _fetch_spawn_pools(self, slots: list[int], spec: tuple) -> None:
        distribution, a, b, clearance = spec
        n = max(SPAWN_POOL_MIN, 8 * self.agents_per_scene)
        requests = []
        for s in slots:
            slot = self._slots[s]
            seed = zlib.crc32(repr((self.seed, s, slot.source, spec)).encode())
            requests.append((slot.worker, SampleSpawn(slot.key, n, clearance, distribution, a, b, seed).to_message()))
        replies = self._pool.call(requests, self.pool_config.step_timeout_s)
        for s, reply in zip(slots, replies):
            if reply.failure is not None:
                self._orphan_worker_slots(reply.worker_id, drop=True, reason=reply.failure)
            elif reply.error is not None:
                raise reply.error
            else:
                positions = np.array(reply.message["positions"], dtype=np.float64).reshape(-1, 3)
                if len(positions) == 0:
                    raise RemoteError(reply.worker_id, "SceneError", f"no free spawn position in slot {s} for {spec}")
                self._spawn_pools[(s, self._slots[s].source, spec)] = positions

    # ----- scene swapping --------------------------------------------------------------------

    def note_resets(self, agents: np.ndarray) -> np.ndarray:
        """Count episode resets per slot; swap scenes that reached ``swap_every_resets``.

        Returns:
            ``(N,)`` bool mask of the agents whose scene was swapped (the env truncates them).
        """
        self._require_started()
        agents = self._agent_index(agents)
        mask = np.zeros(self.num_agents, dtype=bool)
        every = self.scene_config.swap_every_resets
        if every == 0 or len(agents) == 0:
            return mask
        counts = np.bincount(self.agent_scene[agents], minlength=len(self._slots))
        due = []
        for slot in self._slots:
            slot.resets += int(counts[slot.index])
            if slot.resets >= every:
                slot.resets = 0
                slot.source = self.dataset.next_source()
                due.append(slot.index)
        if not due:
            return mask
        self._spawn_pools = {k: v for k, v in self._spawn_pools.items() if k[0] not in due}
        self._maintain()
        live = [s for s in due if self._slots[s].worker is not None]
        self._load([(s, self._slots[s].worker) for s in live])
        self._place_orphans()
        for s in due:
            mask[self.agent_scene == s] = True
        log.info("run %s: swapped scenes of slots %s", self.run_id, due)
        return mask

    # ----- health ----------------------------------------------------------------------------

    def health(self) -> list[dict[str, Any]]:
        """Each live worker's health reply, plus ``local`` and the ``slots`` it serves."""
        self._require_started()
        live = self._pool.live_workers()
        replies = self._pool.call([(w, Health().to_message()) for w in live], self.pool_config.step_timeout_s)
        out = []
        for reply in replies:
            entry = {k: v for k, v in (reply.message or {}).items() if k not in ("version", "type")}
            entry["worker_id"] = reply.worker_id
            entry["local"] = self._pool.is_local(reply.worker_id)
            entry["slots"] = [s.index for s in self._slots if s.worker == reply.worker_id]
            if reply.failure is not None or reply.error is not None:
                entry["error"] = reply.failure or str(reply.error)
            out.append(entry)
        return out

    # ----- placement and recovery ------------------------------------------------------------

    def _maintain(self) -> None:
        """Orphan slots whose worker died or restarted; place orphans; rebalance onto idle workers."""
        live = set(self._pool.live_workers())
        for slot in self._slots:
            if slot.worker is None:
                continue
            if slot.worker not in live:
                self._orphan_worker_slots(slot.worker, drop=True, reason="liveliness token gone")
            elif self._pool.generation(slot.worker) != slot.generation:
                self._orphan_worker_slots(slot.worker, drop=False, reason="restarted")
        if any(s.worker is None for s in self._slots):
            self._place_orphans()
        self._rebalance()

    def _orphan_worker_slots(self, worker_id: str, drop: bool, reason: str) -> None:
        """Orphan every slot of ``worker_id`` (dropping the worker if it failed); mark its agents lost."""
        if drop:
            self._pool.drop(worker_id, reason)
        for slot in self._slots:
            if slot.worker == worker_id:
                slot.worker = None
                self._pending_lost[self.agent_scene == slot.index] = True
                log.warning("run %s: slot %d left worker %s (%s)", self.run_id, slot.index, worker_id, reason)

    def _loads(self) -> dict[str, int]:
        loads = {w: 0 for w in self._pool.live_workers()}
        for slot in self._slots:
            if slot.worker in loads:
                loads[slot.worker] += self.agents_per_scene
        return loads

    def _place_orphans(self) -> None:
        """Load every orphan slot on the least-loaded live workers, until none is left."""
        for _ in range(len(self._slots) + 64):
            orphans = [s for s in self._slots if s.worker is None]
            if not orphans:
                return
            live = self._pool.require_live()
            loads = self._loads()
            plan = []
            for slot in orphans:
                target = min(live, key=lambda w: (loads[w], w))
                loads[target] += self.agents_per_scene
                plan.append((slot.index, target))
            self._load(plan)
        raise NoWorkersError(f"run {self.run_id!r}: could not place scenes after repeated worker failures")

    def _load(self, plan: list[tuple[int, str]]) -> None:
        """LoadScene for each (slot, worker), all in flight; failing workers are dropped."""
        if not plan:
            return
        requests = []
        for s, wid in plan:
            slot = self._slots[s]
            requests.append((wid, LoadScene(slot.key, slot.source, self.cameras, self.drone_radius,
                                            self.multi_agent).to_message()))
        replies = self._pool.call(requests, self.pool_config.startup_timeout_s)
        failed = []
        for (s, wid), reply in zip(plan, replies):
            slot = self._slots[s]
            if reply.failure is not None:
                slot.worker = None
                failed.append((wid, reply.failure))
            elif reply.error is not None:
                raise RemoteError(wid, reply.error.error_type, f"loading {slot.source!r} into slot {s}: {reply.error.message}")
            else:
                slot.worker = wid
                slot.generation = self._pool.generation(wid)
                slot.bounds = np.asarray(reply.message["bounds"], dtype=np.float64).reshape(2, 3)
                slot.metadata = dict(reply.message.get("metadata", {}))
        for wid, reason in failed:
            self._orphan_worker_slots(wid, drop=True, reason=reason)

    def _rebalance(self) -> None:
        """Move scenes from the busiest to idle workers while loads differ by more than one scene.

        The scene is loaded on the new worker before the old one forgets it, so nothing is lost.
        """
        loads = self._loads()
        moves: list[tuple[int, str, str]] = []
        while len(loads) > 1:
            busiest = max(loads, key=lambda w: (loads[w], w))
            idlest = min(loads, key=lambda w: (loads[w], w))
            if loads[busiest] - loads[idlest] <= self.agents_per_scene:
                break
            slot = next(s for s in reversed(self._slots)
                        if s.worker == busiest and s.index not in {m[0] for m in moves})
            moves.append((slot.index, busiest, idlest))
            loads[busiest] -= self.agents_per_scene
            loads[idlest] += self.agents_per_scene
        if not moves:
            return
        log.info("run %s: rebalancing slots %s", self.run_id, [(m[0], m[1], m[2]) for m in moves])
        old = {s: src for s, src, _ in moves}
        self._load([(s, dst) for s, _, dst in moves])
        unload = [(old[s], UnloadScene(self._slots[s].key).to_message()) for s, _, _ in moves
                  if self._slots[s].worker not in (None, old[s])]
        self._pool.call(unload, self.pool_config.step_timeout_s)  # best effort: a failure shows next call

    # ----- input checks ----------------------------------------------------------------------

    def _require_started(self) -> None:
        if not self._started or self._closed:
            raise ConfigError("call Aggregator.start() (or use it as a context manager) before this; "
                              + ("it was closed" if self._closed else "it was not started"))

    def _agent_index(self, agents: np.ndarray | Sequence[int] | None) -> np.ndarray:
        if agents is None:
            return np.arange(self.num_agents, dtype=np.int64)
        idx = np.asarray(agents)
        if idx.dtype == bool:
            if idx.shape != (self.num_agents,):
                raise ConfigError(f"agent mask of shape {idx.shape} must be ({self.num_agents},)")
            return np.flatnonzero(idx)
        if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer) and idx.size:
            raise ConfigError(f"agents must be a 1-D array of agent indices, got shape {idx.shape} dtype {idx.dtype}")
        idx = idx.astype(np.int64)
        if idx.size and (idx.min() < 0 or idx.max() >= self.num_agents):
            raise ConfigError(f"agent indices must be in [0, {self.num_agents}), got {idx.min()}..{idx.max()}")
        return idx

    def _pose_rows(self, poses: np.ndarray, agents: np.ndarray) -> np.ndarray:
        poses = np.asarray(poses)
        if poses.ndim != 2 or poses.shape[1] != 7 or poses.shape[0] not in (self.num_agents, len(agents)):
            raise ConfigError(f"poses of shape {poses.shape} must be ({self.num_agents}, 7) or ({len(agents)}, 7): "
                              "rows [x, y, z, qw, qx, qy, qz]")
        rows = poses[agents] if poses.shape[0] == self.num_agents else poses
        rows = np.array(rows, dtype=np.float32)
        if not np.all(np.isfinite(rows)):
            bad = np.flatnonzero(~np.all(np.isfinite(rows), axis=1))
            raise ConfigError(f"poses of agents {agents[bad][:10].tolist()} are not finite")
        norms = np.linalg.norm(rows[:, 3:], axis=1, keepdims=True)
        if np.any(norms < 1e-6):
            raise ConfigError("poses hold a zero quaternion; quaternions are wxyz and must be unit")
        rows[:, 3:] /= norms
        return rows
