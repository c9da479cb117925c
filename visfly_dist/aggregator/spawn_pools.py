"""Spawn pools: free start positions per slot, scene and distribution, drawn locally.

A pool of :attr:`SpawnPools.size` positions is sampled by the worker serving the slot (one
``sample_spawn`` request, :meth:`SpawnPools.fetch`); resets then draw from it without a round
trip. Each agent draws from its own counter-based stream (:class:`AgentStreams`), so its starts
depend on its seed and on how many draws it made, never on the other agents' resets. A pool is
refreshed in the background once half of it has been drawn and replaced when all of it has: at a
draw count, not a time, so the same seed gives the same positions whatever the timing. The
aggregator decides when to wait for a refresh (it owns the background requests); this module only
keeps the pools and says what is due.
"""

from __future__ import annotations

import functools
import math
import zlib
from dataclasses import dataclass
from typing import Any, NamedTuple, Sequence

import numpy as np

from visfly_dist.aggregator.pool import Pending, WorkerPool
from visfly_dist.errors import ConfigError
from visfly_dist.protocol.messages import SampleSpawn

SPAWN_POOL_MIN = 256
"""Fewest positions in a pool (more with many agents per scene: 8 per agent)."""

__all__ = ["AgentStreams", "PoolKey", "SpawnJob", "SpawnPools", "SpawnSpec", "counter_draws", "spawn_spec"]


class SpawnSpec(NamedTuple):
    """How positions are drawn: ``uniform`` between corners ``a`` and ``b``, or ``normal`` around
    ``a`` with std ``b``, at ``clearance`` metres from any obstacle."""

    distribution: str
    a: tuple[float, float, float]
    b: tuple[float, float, float]
    clearance: float


class PoolKey(NamedTuple):
    """One pool: a slot, the scene source it holds, and the distribution (a tuple: hashed in C, as
    dictionary keys are on every draw)."""

    slot: int
    source: str
    spec: SpawnSpec


@dataclass
class SpawnJob:
    """A ``sample_spawn`` request in flight: a pool's first fetch, or (``refresh``) its next one."""

    pending: Pending
    key: PoolKey
    refresh: bool = False


def spawn_spec(distribution: str, a: Sequence[float], b: Sequence[float], clearance: float) -> SpawnSpec:
    """The checked :class:`SpawnSpec` of a spawn request; ConfigError naming every problem.

    Tasks ask with the same tuples on every reset: those are checked once (a request that fails is
    not remembered, so it fails each time)."""
    if type(a) is tuple and type(b) is tuple:
        try:
            return _remembered_spec(distribution, a, b, clearance)
        except TypeError:  # something in the tuples is not hashable
            pass
    return _spec(distribution, a, b, clearance)


def _spec(distribution: str, a: Sequence[float], b: Sequence[float], clearance: float) -> SpawnSpec:
    plain = _plain_spec(distribution, a, b, clearance)
    return plain if plain is not None else _checked_spec(distribution, a, b, clearance)


_remembered_spec = functools.lru_cache(maxsize=64)(_spec)


_REAL = (float, int, np.floating, np.integer)


def _plain_spec(distribution: str, a: Any, b: Any, clearance: float) -> SpawnSpec | None:
    """:func:`spawn_spec` of a valid request whose corners are tuples or lists of 3 plain numbers
    (what tasks pass on every reset), without NumPy; None for anything else, which
    :func:`_checked_spec` then takes (``float`` of such a number is its float64 value exactly)."""
    if distribution not in ("uniform", "normal") or type(a) not in (tuple, list) or type(b) not in (tuple, list) \
            or len(a) != 3 or len(b) != 3:
        return None
    for v in (*a, *b):
        if not isinstance(v, _REAL) or isinstance(v, bool):
            return None
    va = (float(a[0]), float(a[1]), float(a[2]))
    vb = (float(b[0]), float(b[1]), float(b[2]))
    c = float(clearance)
    if not (all(map(math.isfinite, va)) and all(map(math.isfinite, vb)) and 0 <= c <= 100):
        return None
    if distribution == "uniform" and any(x > y for x, y in zip(va, vb)) or distribution == "normal" and min(vb) < 0:
        return None
    return SpawnSpec(distribution, va, vb, c)


def _checked_spec(distribution: str, a: Sequence[float], b: Sequence[float], clearance: float) -> SpawnSpec:
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
    return SpawnSpec(distribution, (float(va[0]), float(va[1]), float(va[2])),
                     (float(vb[0]), float(vb[1]), float(vb[2])), float(clearance))


def counter_draws(keys: np.ndarray, counters: np.ndarray) -> np.ndarray:
    """One uniform 64-bit draw per ``(key, counter)`` pair (uint64 arrays): splitmix64 over both,
    so a stream is a pure function of its key and position, whatever other streams did."""
    with np.errstate(over="ignore"):
        return _splitmix64(_splitmix64(keys.astype(np.uint64)) ^ counters.astype(np.uint64))


def _occurrence(values: np.ndarray) -> np.ndarray:
    """``(k,)`` uint64: how many times each entry's value came earlier in ``values``."""
    order = np.argsort(values, kind="stable")
    ordered = values[order]
    starts = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]])
    rank = np.arange(len(values)) - np.repeat(starts, np.diff(np.r_[starts, len(values)]))
    out = np.empty(len(values), dtype=np.uint64)
    out[order] = rank
    return out


def _splitmix64(z: np.ndarray) -> np.ndarray:
    z = z + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


class AgentStreams:
    """Per agent, the seed of its spawn draws and how many it made since: draw ``k`` of an agent
    is :func:`counter_draws` of its seed and ``k``."""

    def __init__(self, num_agents: int) -> None:
        self._seed = np.zeros(num_agents, dtype=np.uint64)
        self._mixed = _splitmix64(self._seed)  # the first half of counter_draws, fixed per seed
        self._count = np.zeros(num_agents, dtype=np.uint64)

    def reseed(self, agents: np.ndarray, seeds: int | Sequence[int]) -> None:
        """Agent ``agents[i]`` draws from ``seeds[i]`` from now on; an int ``seeds`` gives agent ``a``
        the seed ``seeds + a`` (as Gymnasium and SB3 seed sub-envs)."""
        given = np.asarray(seeds)
        per_agent = int(given) + agents if given.ndim == 0 else given
        values = np.asarray(per_agent, dtype=np.int64).reshape(-1)
        if len(values) != len(agents):
            raise ConfigError(f"reseed: {len(values)} seeds for {len(agents)} agents")
        self._seed[agents] = values.astype(np.uint64)
        self._mixed[agents] = _splitmix64(self._seed[agents])
        self._count[agents] = 0

    def draw(self, agents: np.ndarray) -> np.ndarray:
        """``(k,)`` uint64: the next draw of each of ``agents`` (an agent listed twice draws twice)."""
        if len(agents) < 2 or (agents[1:] > agents[:-1]).all():  # each agent once, as resets ask
            counters = self._count[agents]
            self._count[agents] = counters + np.uint64(1)
        else:
            counters = self._count[agents] + _occurrence(agents)
            np.add.at(self._count, agents, np.uint64(1))
        return _splitmix64(self._mixed[agents] ^ counters)


class SpawnPools:
    """The pools of one run: their positions, draws since each was (re)filled, refresh generations
    (they seed the refreshes) and refreshes that arrived before their pool was used up.

    Args:
        pool: where ``sample_spawn`` requests go.
        agents_per_scene: sizes the pools (8 positions per agent, at least :data:`SPAWN_POOL_MIN`).
        seed: the run's spawn seed.
        timeout_s: deadline of a ``sample_spawn`` request.
    """

    def __init__(self, pool: WorkerPool, agents_per_scene: int, seed: int, timeout_s: float) -> None:
        self._pool = pool
        self.size = max(SPAWN_POOL_MIN, 8 * agents_per_scene)
        self._seed = seed
        self._timeout_s = timeout_s
        self._positions: dict[PoolKey, np.ndarray] = {}
        self._draws: dict[PoolKey, int] = {}
        self._generation: dict[PoolKey, int] = {}  # refreshes asked for, per pool
        self._next: dict[PoolKey, np.ndarray] = {}  # a refresh that arrived, used once the pool is drawn

    def __contains__(self, key: PoolKey) -> bool:
        return key in self._positions

    def specs_of(self, slot: int) -> set[SpawnSpec]:
        """The distributions drawn from in ``slot`` (of any source it held)."""
        return {k.spec for k in self._positions if k.slot == slot}

    def fetch(self, key: PoolKey, worker: str, scene_key: str, refresh: bool = False) -> SpawnJob:
        """Ask ``worker`` (serving the pool's scene as ``scene_key``) for the pool's positions; a
        refresh is the pool's next generation, seeded apart from the ones before."""
        if refresh:
            self._generation[key] = self._generation.get(key, 0) + 1
        distribution, a, b, clearance = key.spec
        seed = zlib.crc32(repr((self._seed, key.slot, key.source, tuple(key.spec), self._generation.get(key, 0))).encode())
        message = SampleSpawn(scene_key, self.size, clearance, distribution, a, b, seed).to_message()
        (pending,) = self._pool.send([(worker, message)], self._timeout_s)
        return SpawnJob(pending, key, refresh)

    def store(self, job: SpawnJob, positions: np.ndarray) -> None:
        """A fetch answered: a first fetch fills the pool; a refresh waits until the pool is used up."""
        if job.refresh:
            self._next[job.key] = positions
            return
        self._positions[job.key] = positions
        self._draws[job.key] = 0

    def draw(self, key: PoolKey, draws: np.ndarray) -> tuple[np.ndarray, bool]:
        """``(k, 3)`` positions of the pool picked by ``draws`` (uint64, :meth:`AgentStreams.draw`),
        and whether half the pool or more is drawn now (else neither :meth:`wants_refresh` nor
        :meth:`used_up` can hold: nothing to ask)."""
        positions = self._positions[key]
        drawn = self._draws[key] = self._draws[key] + len(draws)
        return positions[draws % len(positions)], drawn >= len(positions) // 2

    def wants_refresh(self, key: PoolKey, refreshing: bool) -> bool:
        """Half the pool was drawn and no refresh is on its way or waiting."""
        return self._draws[key] >= len(self._positions[key]) // 2 and not refreshing and key not in self._next

    def used_up(self, key: PoolKey) -> bool:
        return self._draws[key] >= len(self._positions[key])

    def replace(self, key: PoolKey) -> None:
        """Swap in the refresh that arrived for a used-up pool (a pool without one is drawn again)."""
        if key in self._next:
            self._positions[key] = self._next.pop(key)
            self._draws[key] = 0
