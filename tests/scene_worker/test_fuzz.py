"""Fuzzing the worker: thousands of malformed requests (mutations of valid ones) in-process and a
sample over real Zenoh. Every one gets an error reply of the right type with a non-internal code,
none gets an OK, and the worker then answers a valid step bit-identically."""

from __future__ import annotations

import os
from collections import Counter
from typing import Any, Callable, Iterator

import struct

import msgpack
import numpy as np
import pytest

from tests.helpers import call, client_session
from visfly_dist.errors import ErrorCode
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.codec import MAGIC, PROTOCOL_VERSION, decode, encode
from visfly_dist.protocol.messages import (
    Health, LoadScene, SampleSpawn, ScenePoses, StepRequest, UnloadScene, split_step_result,
)
from visfly_dist.protocol.session import SessionConfig
from visfly_dist.scene_worker.service import SceneWorker

CAMERAS = (CameraSpec(name="depth", width=16, height=12), CameraSpec(name="seg", kind="segmentation", width=8, height=8))
SOURCE = "gen:pillars?seed=1"
OPTIONAL = {"render", "query"}        # may be left out of a valid step
ACCEPTED = {"ProtocolError", "SceneError"}
N_IN_PROCESS = 5_200
N_OVER_ZENOH = 300


def _poses(n: int = 3) -> np.ndarray:
    p = np.zeros((n, 7), np.float32)
    p[:, 0] = np.linspace(1.0, 3.0, n)
    p[:, 2], p[:, 3] = 1.5, 1.0
    return p


def _valid() -> list[dict[str, Any]]:
    """One valid message of every request type, as maps with ``version`` (what goes on the wire)."""
    messages = [
        LoadScene("s1", "gen:empty", CAMERAS).to_message(),
        UnloadScene("s0").to_message(),
        StepRequest((ScenePoses("s0", _poses()),)).to_message(),
        SampleSpawn("s0", 4, 0.2, "uniform", (1, -2, 1), (5, 2, 2), seed=3).to_message(),
        Health().to_message(),
    ]
    return [{"version": PROTOCOL_VERSION, **m} for m in messages]


WRONG_TYPES: list[Any] = ["x", None, [1, 2], {"a": 1}, b"\x00\x01", True, False]
HUGE = [2**64 - 1, -(2**63), 1e300, -1e300, float("nan"), float("inf"), float("-inf")]


def _wrong_for(value: Any) -> list[Any]:
    """Values that can never stand in for ``value`` (an int may replace a float, so none is offered)."""
    if isinstance(value, bool):
        return [0, 1, "true", None, [True]]
    if isinstance(value, (int, float)):
        return ["1", None, [1.0], {"v": 1}, b"1", True, False]
    if isinstance(value, str):
        return [1, 2.5, None, [value], True, b"s0"]
    if isinstance(value, np.ndarray):
        return [value.tolist(), "poses", None, 3.0, True]
    return [x for x in WRONG_TYPES if type(x) is not type(value)]


def _bad_arrays(rng: np.random.Generator) -> list[np.ndarray]:
    p = _poses()
    nan, inf, long_q, far = p.copy(), p.copy(), p.copy(), p.copy()
    nan[1, 0], inf[0, 5], long_q[0, 3], far[2, 1] = np.nan, np.inf, 3.0, 1e7
    return [p[:, :6].copy(), p.reshape(3, 7, 1), p.astype(np.int32), p.astype(np.uint8), p.astype(bool),
            p.astype(np.int64), np.zeros((2, 7), np.float32), nan, inf, long_q, far, p.astype(np.uint16),
            rng.normal(size=(4, 8)).astype(np.float32), np.zeros(7, np.float32)]


def _mutate_camera(rng: np.random.Generator) -> dict[str, Any]:
    cam = CAMERAS[0].to_dict()
    field, value = [("height", True), ("width", False), ("width", 0), ("width", 10**6), ("height", 2.0),
                    ("hfov_deg", "90"), ("hfov_deg", float("nan")), ("hfov_deg", 1e300), ("offset", None),
                    ("offset", "abc"), ("offset", [0, 0]), ("offset", [0, 0, float("inf")]), ("rotation", "wxyz"),
                    ("rotation", None), ("rotation", [0, 0, 0, 0]), ("rotation", [True, 0, 0, 0]), ("kind", "lidar"),
                    ("kind", 3), ("name", ""), ("name", "a/b"), ("name", 5), ("near", -1.0), ("far", 1e300),
                    ("near", "0.1"), ("zoom", 2)][rng.integers(25)]
    cam[field] = value
    return cam


BAD_KEYS = ["s0\n", "\ns0", "a/b", "*", "**", "", "k" * 300, "k" * 100, "s 0", "s0?x", "é", "no_such_scene"]
BAD_SOURCES = ["gen:garage-stones?density=1e300", "gen:garage-stones?density=3", "gen:pillars?density=-1",
               "gen:pillars?seed=-1", "gen:pillars?colour=3", "gen:volcano", "gen:garage-stones?max_radius=1e9",
               "../../etc/passwd", "/etc/passwd", "no/such.glb", "", "x" * 5000, "a\x00b", "gen:empty?seed=1.5",
               "gen:gap-walls?gap_width=nan"]


def _mutations(rng: np.random.Generator) -> list[Callable[[dict[str, Any]], Any]]:
    """Each takes a valid message and returns an invalid one (a map, or raw bytes)."""

    def wrong_type(m):
        key = [k for k in m if k != "version"][rng.integers(len(m) - 1)]
        values = _wrong_for(m[key])
        return {**m, key: values[rng.integers(len(values))]}

    def numbers(m):
        keys = [k for k, v in m.items() if isinstance(v, (int, float)) and not isinstance(v, bool) and k != "version"]
        if not keys:
            return {**m, "type": HUGE[rng.integers(len(HUGE))]}
        key = keys[rng.integers(len(keys))]
        bad = [True, False, *HUGE] if key in ("n", "seed") else [True, False, *HUGE[2:]]
        if key == "seed":
            bad += [-1, -(2**40)]
        return {**m, key: bad[rng.integers(len(bad))]}

    def missing(m):
        keys = [k for k in m if k not in OPTIONAL]
        key = keys[rng.integers(len(keys))]
        return {k: v for k, v in m.items() if k != key}

    def extra(m):
        return {**m, f"extra_{rng.integers(100)}": [None, 1, "x", True][rng.integers(4)]}

    def version(m):
        return {**m, "version": [True, float(PROTOCOL_VERSION), PROTOCOL_VERSION + 1, PROTOCOL_VERSION - 1, 0,
                                 str(PROTOCOL_VERSION), None, -1, 2**64 - 1][rng.integers(9)]}

    def truncated(m):
        body = encode({k: v for k, v in m.items() if k != "version"})
        return body[: rng.integers(len(body))]

    def garbage(m):
        return rng.bytes(int(rng.integers(1, 64)))

    def bad_type_name(m):
        return {**m, "type": ["explode", "", "STEP", "step ", 7, None, ["step"]][rng.integers(7)]}

    def specific(m):
        """A mutation that knows the message type: arrays, cameras, keys, sources, vectors."""
        kind = m["type"]
        if kind == "step":
            choice = rng.integers(4)
            if choice == 0:
                arrays = _bad_arrays(rng)
                return {**m, "poses": arrays[rng.integers(len(arrays))]}
            if choice == 1:
                return {**m, "keys": [BAD_KEYS[rng.integers(len(BAD_KEYS))]]}
            if choice == 2:
                return {**m, "keys": [[1, 2], "s0", None, {"poses": _poses()}][rng.integers(4)]}
            return {**m, "counts": [np.array([2], np.int32), np.array([-1], np.int64), np.array([1.0]), [1],
                                    np.array([1, 0], np.int32), None][rng.integers(6)]}
        if kind == "load_scene":
            choice = rng.integers(4)
            if choice == 0:
                return {**m, "cameras": [_mutate_camera(rng)]}
            if choice == 1:
                return {**m, "source": BAD_SOURCES[rng.integers(len(BAD_SOURCES))]}
            if choice == 2:
                return {**m, "cameras": [[], [CAMERAS[0].to_dict()] * 2, [CAMERAS[0].to_dict()] * 17,
                                         ["depth"]][rng.integers(4)]}
            return {**m, "scene_key": BAD_KEYS[rng.integers(len(BAD_KEYS) - 1)]}
        if kind == "sample_spawn":
            key = ["a", "b"][rng.integers(2)]
            return {**m, key: [[1, 2], [1, 2, 3, 4], ["1", 2, 3], [None, 0, 0], [float("nan"), 0, 0],
                               [1e300, 0, 0], "abc", None, [True, 0, 0]][rng.integers(9)]}
        if kind == "unload_scene":
            return {**m, "scene_key": BAD_KEYS[rng.integers(len(BAD_KEYS))]}
        return {**m, "verbose": True}

    return [wrong_type, numbers, missing, extra, version, truncated, garbage, bad_type_name, specific, specific]


def malformed(seed: int, count: int) -> Iterator[bytes]:
    """``count`` encoded malformed requests, reproducible from ``seed``."""
    rng = np.random.default_rng(seed)
    valid, mutations = _valid(), _mutations(rng)
    for _ in range(count):
        message = valid[rng.integers(len(valid))]
        bad = mutations[rng.integers(len(mutations))](message)
        if isinstance(bad, bytes):
            yield bad
        else:
            yield _frame_any(bad)


def _frame_any(message: dict) -> bytes:
    """The codec's framing for any message and any dtype (the codec itself refuses to send odd ones)."""
    tail: list[bytes] = []
    size = 0

    def array_form(obj: Any) -> Any:
        nonlocal size
        if isinstance(obj, np.ndarray):
            data = obj.tobytes()
            ref = {"__nd__": 1, "dtype": obj.dtype.str, "shape": list(obj.shape), "offset": size, "nbytes": len(data)}
            tail.append(data)
            size += len(data)
            return ref
        raise TypeError(type(obj))

    header = msgpack.packb(message, default=array_form, use_bin_type=True)
    return struct.pack("<4sI", MAGIC, len(header)) + header + b"".join(tail)


def _check_error(ok: bool, reply: dict[str, Any], payload: bytes, seen: Counter) -> None:
    assert not ok, f"an invalid request got an OK reply: {payload[:200]!r} -> {reply}"
    assert reply["type"] == "error" and reply["error"] in ACCEPTED, (payload[:200], reply)
    assert reply["code"] in set(ErrorCode) - {ErrorCode.INTERNAL}, (payload[:200], reply)
    seen[(reply["error"], reply["code"])] += 1


def _reference_step(respond: Callable[[dict], tuple[bool, dict]]) -> dict[str, Any]:
    ok, reply = respond(StepRequest((ScenePoses("s0", _poses(5)),)).to_message())
    assert ok, reply
    return split_step_result(reply)[0]


def _assert_identical(a: dict[str, Any], b: dict[str, Any]) -> None:
    assert a.keys() == b.keys() and a["images"].keys() == b["images"].keys()
    for name in a["images"]:
        assert a["images"][name].tobytes() == b["images"][name].tobytes(), name
    for name in ("collision", "inside", "nearest", "distance"):
        assert a[name].tobytes() == b[name].tobytes(), name


def test_thousands_of_malformed_requests_in_process(scene_root):
    worker = SceneWorker("fuzz", SessionConfig(), [scene_root], backend="raycast", worker_id="w0")
    try:
        def respond(message):
            ok, body = worker.handle(encode(message))
            return ok, decode(body)

        assert respond(LoadScene("s0", SOURCE, CAMERAS).to_message())[0]
        before = _reference_step(respond)
        seen: Counter = Counter()
        for payload in malformed(seed=0, count=N_IN_PROCESS):
            ok, body = worker.handle(payload)
            _check_error(ok, decode(body), payload, seen)
        assert sum(seen.values()) == N_IN_PROCESS
        # Every kind of error reply was exercised, not just the codec's.
        assert {code for _, code in seen} >= {"bad_request", "too_large", "unknown_scene", "scene_error"}, seen
        _assert_identical(_reference_step(respond), before)
        assert respond(Health().to_message())[1]["scenes"] == ["s0"]
    finally:
        worker.close()


@pytest.mark.worker
def test_malformed_requests_over_zenoh(worker_factory):
    proc = worker_factory(f"fuzz{os.getpid()}", shm=True)
    with client_session(proc.endpoint) as session:
        def respond(message):
            return call(session, proc.rpc_key, message)

        assert respond(LoadScene("s0", SOURCE, CAMERAS).to_message())[0]
        before = _reference_step(respond)
        seen: Counter = Counter()
        for payload in malformed(seed=1, count=N_OVER_ZENOH):
            ok, reply = call(session, proc.rpc_key, payload)
            _check_error(ok, reply, payload, seen)
        _assert_identical(_reference_step(respond), before)
        assert proc.poll() is None and "Traceback" not in proc.stderr_text()
