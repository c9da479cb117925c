"""Message types of the worker protocol, with their validation.

The aggregator builds requests with the ``*.to_message()`` methods; the worker turns a decoded map
into a typed request with :func:`parse_request`, which raises :class:`ProtocolError` naming what
is wrong. Replies are plain maps built by the worker (see each request's docstring).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from visfly_dist.errors import ConfigError, ProtocolError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.image_segment import SegmentTarget
from visfly_dist.protocol.keys import CHUNK_PATTERN, MAX_CHUNK_CHARS, check_chunk

MAX_AGENTS_PER_REQUEST = 100_000
MAX_CAMERAS = 16
MAX_SCENES_PER_REQUEST = 1024
MAX_SOURCE_CHARS = 4096
MAX_TIME_S = 1e9


@dataclass(frozen=True)
class LoadScene:
    """Load (or replace) a scene under ``scene_key``.

    ``source`` is a path relative to one of the worker's scene roots (a scene directory, a mesh
    file or a Habitat ``*.scene_instance.json``) or a generator spec ``gen:KIND?seed=S&key=value``.
    Reply ``{"type": "scene_loaded", "scene_key", "bounds": (2, 3) f64, "num_triangles",
    "num_objects", "backend", "metadata": {...}}``.
    """

    scene_key: str
    source: str
    cameras: tuple[CameraSpec, ...]
    drone_radius: float = 0.1
    multi_agent: bool = False
    type: str = field(default="load_scene", init=False)

    def to_message(self) -> dict[str, Any]:
        return {"type": self.type, "scene_key": self.scene_key, "source": self.source,
                "cameras": [c.to_dict() for c in self.cameras], "drone_radius": float(self.drone_radius),
                "multi_agent": bool(self.multi_agent)}


@dataclass(frozen=True)
class UnloadScene:
    """Forget a scene. Reply ``{"type": "ok"}``."""

    scene_key: str
    type: str = field(default="unload_scene", init=False)

    def to_message(self) -> dict[str, Any]:
        return {"type": self.type, "scene_key": self.scene_key}


@dataclass(frozen=True)
class ScenePoses:
    """Poses of the agents in one scene: ``(n, 7)`` rows ``[x, y, z, qw, qx, qy, qz]`` (world), and
    the scene's simulation time, s (where its moving obstacles are; 0 when the request has none)."""

    scene_key: str
    poses: np.ndarray
    time: float = 0.0

    def to_message(self) -> dict[str, Any]:
        return {"scene_key": self.scene_key, "poses": np.ascontiguousarray(self.poses, dtype=np.float32)}


class StepRequest:
    """Render every camera of every agent and query obstacles, for several scene entries at once.

    On the wire the entries travel as one pose array: ``{"keys": [scene_key, ...], "counts": (m,)
    int32, "poses": (sum(counts), 7) f32}``; entry ``i`` owns the next ``counts[i]`` rows. A key may
    appear more than once (e.g. the spawn poses of a scene's reset agents next to its flying ones);
    in multi-agent scenes the drones of one entry see each other. Optional ``"times": (m,) f64``
    gives each entry's simulation time in seconds (where the moving obstacles are drawn and
    queried; absent: 0 for every entry): the worker keeps no clock of its own. Optional
    ``"image_segment"`` (:class:`~visfly_dist.protocol.image_segment.SegmentTarget`) asks for the
    images in a shared-memory file on the learner's host instead of in the reply.

    Reply ``{"type": "step_result", "counts": (m,) int32, "images": {camera_name: (total, C, H, W)},
    "collision": (total,) bool, "inside": (total,) bool, "nearest": (total, 3) f32 world point,
    "distance": (total,) f32 (capped at search_radius), "timings": {stage: seconds}}``: rows in
    request order, so the receiver scatters each array with one index. With an image segment the
    worker could use, ``"images"`` is empty and ``"images_in_segment": true``; with one it could
    not open or whose nonce differs, the images are inline and ``"segment_refused"`` says why.

    The request keeps the wire's arrays (no object per entry): build one from per-scene
    :class:`ScenePoses` (tools, tests) or with :meth:`from_arrays` (what :func:`parse_request` does).

    Attributes:
        keys: ``(m,)`` scene key of each entry.
        counts: ``(m,)`` int64 agents of each entry.
        poses: ``(sum(counts), 7)`` float64 rows, entry after entry.
        times: ``(m,)`` float64 simulation time of each entry, s.
    """

    type = "step"
    __slots__ = ("keys", "counts", "poses", "times", "render", "query", "search_radius", "image_segment")
    keys: tuple[str, ...]
    counts: np.ndarray
    poses: np.ndarray
    times: np.ndarray
    render: bool
    query: bool
    search_radius: float
    image_segment: SegmentTarget | None

    def __init__(self, scenes: Sequence[ScenePoses] = (), render: bool = True, query: bool = True,
                 search_radius: float = 5.0, image_segment: SegmentTarget | None = None) -> None:
        poses = [np.asarray(s.poses, dtype=np.float64).reshape(-1, 7) for s in scenes]
        self._set(tuple(s.scene_key for s in scenes), np.array([len(p) for p in poses], dtype=np.int64),
                  np.concatenate(poses) if poses else np.zeros((0, 7)),
                  np.array([s.time for s in scenes], dtype=np.float64), render, query, search_radius, image_segment)

    @classmethod
    def from_arrays(cls, keys: Sequence[str], counts: np.ndarray, poses: np.ndarray, times: np.ndarray,
                    render: bool = True, query: bool = True, search_radius: float = 5.0,
                    image_segment: SegmentTarget | None = None) -> "StepRequest":
        """A request straight from the wire's arrays (already validated: see :func:`parse_request`)."""
        request = cls.__new__(cls)
        request._set(tuple(keys), counts, poses, times, render, query, search_radius, image_segment)
        return request

    def _set(self, keys: tuple[str, ...], counts: np.ndarray, poses: np.ndarray, times: np.ndarray, render: bool,
             query: bool, search_radius: float, image_segment: SegmentTarget | None) -> None:
        for name, value in zip(self.__slots__, (keys, counts, poses, times, render, query, search_radius,
                                                image_segment)):
            object.__setattr__(self, name, value)

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(f"StepRequest is immutable; cannot set {name!r}")

    def __repr__(self) -> str:
        return (f"StepRequest({len(self.keys)} entries, {len(self.poses)} agents, render={self.render}, "
                f"query={self.query}, search_radius={self.search_radius}, image_segment={self.image_segment})")

    def bounds(self) -> list[tuple[int, int]]:
        """``(start, end)`` rows of each entry in :attr:`poses`."""
        ends = np.cumsum(self.counts).tolist()
        return list(zip([0, *ends[:-1]], ends))

    @property
    def scenes(self) -> tuple[ScenePoses, ...]:
        """The entries as :class:`ScenePoses` (views on :attr:`poses`; for tools and tests)."""
        return tuple(ScenePoses(key, self.poses[start:end], t) for key, (start, end), t
                     in zip(self.keys, self.bounds(), self.times.tolist()))

    def to_message(self) -> dict[str, Any]:
        return step_message(list(self.keys), self.counts, self.poses, self.render, self.query, self.search_radius,
                            self.times if np.any(self.times != 0) else None, self.image_segment)


def step_message(keys: list[str], counts: np.ndarray, poses: np.ndarray, render: bool = True, query: bool = True,
                 search_radius: float = 5.0, times: np.ndarray | None = None,
                 image_segment: SegmentTarget | None = None) -> dict[str, Any]:
    """A step request's wire map built straight from arrays (the aggregator's hot path).

    ``times``: ``(len(keys),)`` simulation time of each entry, s; None leaves the field out (t = 0).
    ``image_segment``: where the worker should put the images (None: in the reply).
    """
    msg = {"type": "step", "keys": keys, "counts": np.asarray(counts, dtype=np.int32),
           "poses": np.ascontiguousarray(poses, dtype=np.float32), "render": bool(render), "query": bool(query),
           "search_radius": float(search_radius)}
    if times is not None:
        msg["times"] = np.ascontiguousarray(times, dtype=np.float64)
    if image_segment is not None:
        msg["image_segment"] = image_segment.to_message()
    return msg


def split_step_result(reply: Mapping[str, Any]) -> list[dict[str, Any]]:
    """A ``step_result`` reply cut back into one map per request entry (tests and tools)."""
    counts = np.asarray(reply["counts"], dtype=np.int64)
    ends = np.cumsum(counts)
    out = []
    for start, end in zip(ends - counts, ends):
        entry = {"images": {name: img[start:end] for name, img in reply.get("images", {}).items()}}
        for key in ("collision", "inside", "nearest", "distance"):
            if key in reply:
                entry[key] = reply[key][start:end]
        out.append(entry)
    return out


@dataclass(frozen=True)
class SampleSpawn:
    """Sample ``n`` positions in free space at ``clearance`` from any obstacle.

    ``distribution`` is ``"uniform"`` (``a`` = low, ``b`` = high corner) or ``"normal"``
    (``a`` = mean, ``b`` = std). Reply ``{"type": "spawn", "positions": (n, 3) f32}``.
    """

    scene_key: str
    n: int
    clearance: float
    distribution: str
    a: tuple[float, float, float]
    b: tuple[float, float, float]
    seed: int = 0
    type: str = field(default="sample_spawn", init=False)

    def to_message(self) -> dict[str, Any]:
        return {"type": self.type, "scene_key": self.scene_key, "n": int(self.n), "clearance": float(self.clearance),
                "distribution": self.distribution, "a": [float(v) for v in self.a], "b": [float(v) for v in self.b],
                "seed": int(self.seed)}


@dataclass(frozen=True)
class Health:
    """Ask for the worker's state. Reply ``{"type": "health", "worker_id", "pid", "host", "backend",
    "scenes": [keys], "uptime_s", "timings": {stage: {"count": int, "total_s": float}}}``."""

    type: str = field(default="health", init=False)

    def to_message(self) -> dict[str, Any]:
        return {"type": self.type}


REQUEST_TYPES = ("load_scene", "unload_scene", "step", "sample_spawn", "health")
Request = LoadScene | UnloadScene | StepRequest | SampleSpawn | Health


REQUEST_FIELDS: dict[str, frozenset[str]] = {
    "health": frozenset(),
    "unload_scene": frozenset({"scene_key"}),
    "load_scene": frozenset({"scene_key", "source", "cameras", "drone_radius", "multi_agent"}),
    "sample_spawn": frozenset({"scene_key", "n", "clearance", "distribution", "a", "b", "seed"}),
    "step": frozenset({"keys", "counts", "poses", "render", "query", "search_radius", "times", "image_segment"}),
}
"""The fields each request type may carry besides ``version`` and ``type``; others are refused."""
MAX_SEED = 2**63 - 1


def _get(msg: Mapping[str, Any], key: str, kind: type | tuple[type, ...], what: str) -> Any:
    if key not in msg:
        raise ProtocolError(f"{what}: missing field {key!r}")
    value = msg[key]
    expected = "a number" if kind == (int, float) else kind.__name__  # type: ignore[union-attr]
    if (isinstance(value, bool) and kind is not bool) or not isinstance(value, kind):
        raise ProtocolError(f"{what}: field {key!r} must be {expected}, got {type(value).__name__}")
    return value


def _flag(msg: Mapping[str, Any], key: str, what: str) -> bool:
    """An optional boolean field (default True); anything but a bool is refused."""
    return _get(msg, key, bool, what) if key in msg else True


def _finite(value: Any, what: str, lo: float, hi: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ProtocolError(f"{what}={value!r} must be a number, got {type(value).__name__}")
    v = float(value)
    if not math.isfinite(v) or not lo <= v <= hi:
        raise ProtocolError(f"{what}={value!r} must be finite and in [{lo}, {hi}]")
    return v


def _key(msg: Mapping[str, Any], what: str) -> str:
    try:
        return check_chunk(_get(msg, "scene_key", str, what), "scene_key")
    except ConfigError as exc:
        raise ProtocolError(f"{what}: {exc}") from None


_KEYS = re.compile(rf"{CHUNK_PATTERN}{{1,{MAX_CHUNK_CHARS}}}(?:\n{CHUNK_PATTERN}{{1,{MAX_CHUNK_CHARS}}})*")
"""Keys joined by newlines (a character no key may hold): one match checks them all."""


def _scene_keys(keys: list[Any], what: str) -> None:
    """ProtocolError naming the first bad entry unless every key is a valid key chunk (one regex)."""
    if not keys:
        return
    if all(type(k) is str for k in keys):
        joined = "\n".join(keys)
        if joined.count("\n") == len(keys) - 1 and _KEYS.fullmatch(joined):  # no key holds a newline
            return
    for i, key in enumerate(keys):
        _key({"scene_key": key}, f"{what}.keys[{i}]")
    raise AssertionError("the bulk key check refused keys that each pass check_chunk")  # pragma: no cover


def _vec3(msg: Mapping[str, Any], key: str, what: str) -> tuple[float, float, float]:
    value = _get(msg, key, list, what)
    if len(value) != 3:
        raise ProtocolError(f"{what}: {key} must be a list of 3 numbers, got {len(value)} items")
    return tuple(_finite(v, f"{what}.{key}", -1e6, 1e6) for v in value)  # type: ignore[return-value]


def _no_extra(msg: Mapping[str, Any], allowed: frozenset[str], what: str) -> None:
    extra = set(msg) - allowed
    if extra:
        raise ProtocolError(f"{what}: unknown field(s) {sorted(map(str, extra))}; accepted: {sorted(allowed)}")


def _poses(value: Any, what: str) -> np.ndarray:
    """The poses as a new float64 array; ProtocolError naming the first problem.

    The common case (every pose valid) costs a handful of NumPy calls: min and max bound the
    positions and the squared quaternion norms at once, and NaN fails every comparison. Only a
    refused array goes through the checks one by one, to say what is wrong.
    """
    if not isinstance(value, np.ndarray):
        raise ProtocolError(f"{what}: poses must be an array, got {type(value).__name__}")
    if value.dtype not in (np.float32, np.float64):
        raise ProtocolError(f"{what}: poses dtype {value.dtype} must be float32 or float64")
    if value.ndim != 2 or value.shape[1] != 7:
        raise ProtocolError(f"{what}: poses shape {value.shape} must be (n, 7): x y z qw qx qy qz")
    if value.shape[0] > MAX_AGENTS_PER_REQUEST:
        raise ProtocolError(f"{what}: {value.shape[0]} poses exceed the bound {MAX_AGENTS_PER_REQUEST}")
    poses = value.astype(np.float64)
    if not len(poses):
        return poses
    positions, quats = poses[:, :3], poses[:, 3:]
    norms2 = np.einsum("ij,ij->i", quats, quats)
    if -1e6 <= positions.min() and positions.max() <= 1e6 and _UNIT_NORM2[0] <= norms2.min() \
            and norms2.max() <= _UNIT_NORM2[1]:
        return poses
    if not np.all(np.isfinite(value)):
        raise ProtocolError(f"{what}: poses contain NaN or infinite values")
    if np.any(np.abs(positions) > 1e6):
        raise ProtocolError(f"{what}: positions beyond 1e6 m")
    norms = np.sqrt(norms2)
    raise ProtocolError(f"{what}: quaternions must be unit (norms range {norms.min():.3g}..{norms.max():.3g})")


_UNIT_NORM2 = ((1.0 - 1e-2) ** 2, (1.0 + 1e-2) ** 2)
"""Squared quaternion norms accepted: the norm within 1e-2 of 1."""


def parse_request(msg: Mapping[str, Any]) -> Request:
    """Validate a decoded message and return the typed request; ProtocolError otherwise.

    Strict: numbers are never bools, flags are only bools, unknown fields are refused.
    """
    kind = msg.get("type")
    if not isinstance(kind, str) or kind not in REQUEST_TYPES:
        raise ProtocolError(f"unknown message type {kind!r}; valid types: {', '.join(REQUEST_TYPES)}")
    what = kind
    _no_extra(msg, REQUEST_FIELDS[kind] | {"version", "type"}, what)
    if kind == "health":
        return Health()
    if kind == "unload_scene":
        return UnloadScene(_key(msg, what))
    if kind == "load_scene":
        source = _get(msg, "source", str, what)
        if not source or len(source) > MAX_SOURCE_CHARS or "\x00" in source:
            raise ProtocolError(f"{what}: source must be a non-empty string under {MAX_SOURCE_CHARS} chars")
        cams = _get(msg, "cameras", list, what)
        if not 1 <= len(cams) <= MAX_CAMERAS:
            raise ProtocolError(f"{what}: {len(cams)} cameras must be between 1 and the bound {MAX_CAMERAS}")
        try:
            cameras = tuple(CameraSpec.from_dict(c) for c in cams)
        except ConfigError as exc:
            raise ProtocolError(f"{what}: {exc}") from None
        names = [c.name for c in cameras]
        if len(set(names)) != len(names):
            raise ProtocolError(f"{what}: camera names {names} must be unique")
        radius = _finite(_get(msg, "drone_radius", (int, float), what), "drone_radius", 0.0, 10.0)
        multi = _get(msg, "multi_agent", bool, what)
        return LoadScene(_key(msg, what), source, cameras, radius, multi)
    if kind == "sample_spawn":
        n = _get(msg, "n", int, what)
        if not 1 <= n <= MAX_AGENTS_PER_REQUEST:
            raise ProtocolError(f"{what}: n={n} must be in [1, {MAX_AGENTS_PER_REQUEST}]")
        dist = _get(msg, "distribution", str, what)
        if dist not in ("uniform", "normal"):
            raise ProtocolError(f"{what}: distribution={dist!r} must be 'uniform' or 'normal'")
        a, b = _vec3(msg, "a", what), _vec3(msg, "b", what)
        if dist == "uniform" and any(lo > hi for lo, hi in zip(a, b)):
            raise ProtocolError(f"{what}: uniform low {a} must not exceed high {b}")
        if dist == "normal" and any(s < 0 for s in b):
            raise ProtocolError(f"{what}: normal std {b} must be non-negative")
        seed = _get(msg, "seed", int, what)
        if not 0 <= seed <= MAX_SEED:
            raise ProtocolError(f"{what}: seed={seed} must be in [0, 2**63 - 1]")
        clearance = _finite(_get(msg, "clearance", (int, float), what), "clearance", 0.0, 100.0)
        return SampleSpawn(_key(msg, what), n, clearance, dist, a, b, seed)
    # step
    keys = _get(msg, "keys", list, what)
    if len(keys) > MAX_SCENES_PER_REQUEST:
        raise ProtocolError(f"{what}: {len(keys)} scene entries exceed the bound {MAX_SCENES_PER_REQUEST}")
    _scene_keys(keys, what)
    counts = msg.get("counts")
    if not isinstance(counts, np.ndarray) or counts.dtype.kind not in "iu" or counts.shape != (len(keys),):
        raise ProtocolError(f"{what}: counts must be an integer array of shape ({len(keys)},), one per key")
    counts = counts.astype(np.int64)
    if len(counts) and counts.min() < 0:
        raise ProtocolError(f"{what}: counts must be non-negative")
    poses = _poses(msg.get("poses"), what)
    if int(counts.sum()) != poses.shape[0]:
        raise ProtocolError(f"{what}: counts add up to {int(counts.sum())} but poses has {poses.shape[0]} rows")
    if "times" in msg:
        times = msg["times"]
        if not isinstance(times, np.ndarray) or times.dtype.kind != "f" or times.shape != (len(keys),):
            raise ProtocolError(f"{what}: times must be a float array of shape ({len(keys)},), one per key")
        times = times.astype(np.float64)
        if len(times) and not (-MAX_TIME_S <= times.min() and times.max() <= MAX_TIME_S):  # NaN fails too
            raise ProtocolError(f"{what}: times must be finite seconds within +-{MAX_TIME_S:g}")
    else:
        times = np.zeros(len(keys))
    radius = _finite(_get(msg, "search_radius", (int, float), what), "search_radius", 0.0, 1e4)
    segment = SegmentTarget.parse(msg["image_segment"]) if "image_segment" in msg else None
    return StepRequest.from_arrays(keys, counts, poses, times, _flag(msg, "render", what), _flag(msg, "query", what),
                                   radius, segment)
