"""The msgpack codec: round trips of every message and array dtype; every malformed payload rejected."""

from __future__ import annotations

import struct

import msgpack
import numpy as np
import pytest

from visfly_dist.errors import ErrorCode, ProtocolError, RemoteError
from visfly_dist.protocol import codec
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.codec import PROTOCOL_VERSION, decode, encode, error_message
from visfly_dist.protocol.messages import (
    Health, LoadScene, SampleSpawn, ScenePoses, StepRequest, UnloadScene, parse_request,
)

IDENTITY = [1.0, 0.0, 0.0, 0.0]


def _poses(n: int) -> np.ndarray:
    return np.array([[i, 2.0 * i, 1.5, *IDENTITY] for i in range(n)], dtype=np.float32).reshape(n, 7)


REQUESTS = [
    LoadScene("s0", "gen:pillars?seed=1", (CameraSpec(), CameraSpec(name="rgb", kind="rgb", width=32, height=24)),
              drone_radius=0.15, multi_agent=True),
    UnloadScene("s0"),
    StepRequest((ScenePoses("s0", _poses(3)), ScenePoses("s1", _poses(0))), render=True, query=False, search_radius=4.0),
    SampleSpawn("s0", 5, 0.3, "uniform", (-1.0, -2.0, 0.5), (1.0, 2.0, 2.5), seed=7),
    Health(),
]


@pytest.mark.parametrize("request_", REQUESTS, ids=lambda r: r.type)
def test_every_request_round_trips(request_):
    parsed = parse_request(decode(encode(request_.to_message())))
    assert type(parsed) is type(request_)
    if isinstance(request_, StepRequest):
        assert (parsed.render, parsed.query, parsed.search_radius) == (True, False, 4.0)
        for got, sent in zip(parsed.scenes, request_.scenes):
            assert got.scene_key == sent.scene_key
            np.testing.assert_array_equal(got.poses, sent.poses)
            assert got.poses.dtype == np.float64
    else:
        assert parsed == request_


@pytest.mark.parametrize("dtype", ["bool", "uint8", "uint16", "int32", "int64", "float32", "float64"])
@pytest.mark.parametrize("shape", [(), (0,), (5,), (2, 3, 4), (1, 1, 2, 3)])
def test_arrays_of_every_allowed_dtype_round_trip(dtype, shape):
    rng = np.random.default_rng(0)
    arr = np.asarray(rng.random(shape) * 100).astype(dtype)
    out = decode(encode({"type": "x", "a": arr, "nested": {"b": [arr]}}))
    for got in (out["a"], out["nested"]["b"][0]):
        assert got.dtype == arr.dtype and got.shape == arr.shape
        np.testing.assert_array_equal(got, arr)


def test_non_contiguous_arrays_travel_as_their_values():
    arr = np.arange(24, dtype=np.float32).reshape(4, 6)[:, ::2]
    np.testing.assert_array_equal(decode(encode({"type": "x", "a": arr}))["a"], arr)


def test_replies_round_trip_with_plain_values_and_numpy_scalars():
    reply = {"type": "step_result", "counts": np.array([2], np.int32), "images": {"depth": np.ones((2, 1, 4, 4), np.float32)},
             "distance": np.float32(1.5), "n": np.int64(3), "t": (1, 2), "timings": {"total_s": 0.01}}
    out = decode(encode(reply))
    assert out["version"] == PROTOCOL_VERSION and out["n"] == 3 and out["t"] == [1, 2]
    assert out["images"]["depth"].shape == (2, 1, 4, 4) and out["distance"] == 1.5


def test_error_message_carries_type_code_and_message():
    out = decode(error_message("SceneError", ErrorCode.UNKNOWN_SCENE, "no such scene"))
    assert out == {"version": PROTOCOL_VERSION, "type": "error", "error": "SceneError", "code": "unknown_scene",
                   "message": "no such scene"}
    err = RemoteError.from_reply("w1", out)
    assert err.code == ErrorCode.UNKNOWN_SCENE and err.error_type == "SceneError" and err.message == "no such scene"
    assert RemoteError.from_reply("w1", {"error": "X", "code": "from_the_future", "message": ""}).code == "internal"
    with pytest.raises(ValueError, match="not_a_code"):
        error_message("SceneError", "not_a_code", "x")


@pytest.mark.parametrize("version", [True, 3.0, "3", None, 1, 2, 4])
def test_only_the_exact_int_version_is_accepted(version):  # 1, 2: workers from before image segments, memfd segments
    with pytest.raises(ProtocolError, match="protocol version"):
        decode(_raw({"version": version, "type": "health"}, tail=b""))


def test_encode_rejects_what_cannot_travel():
    with pytest.raises(ProtocolError, match="dtype complex128 cannot travel"):
        encode({"type": "x", "a": np.zeros(2, complex)})
    with pytest.raises(ProtocolError, match="cannot encode object"):
        encode({"type": "x", "a": object()})
    with pytest.raises(ProtocolError, match="needs a 'type'"):
        encode({"a": 1})


def _raw(obj, tail: bytes = b"\0" * 8) -> bytes:
    """A framed payload: our prefix, ``obj`` as the msgpack header, ``tail`` as the array bytes."""
    header = msgpack.packb(obj, use_bin_type=True)
    return struct.pack("<4sI", codec.MAGIC, len(header)) + header + tail


def _nd(dtype="<f4", shape=(2,), offset=0, nbytes=8):
    return {"__nd__": 1, "dtype": dtype, "shape": list(shape), "offset": offset, "nbytes": nbytes}


@pytest.mark.parametrize("payload, match", [
    (b"", "does not start with the framing"),
    (b"\xc1\xff\x00garbage", "does not start with the framing"),
    (codec.MAGIC + b"\xff\xff\x00\x00", "header length 65535 exceeds"),
    (codec.MAGIC + b"\x03\x00\x00\x00\xc1\xff\x00", "not a valid msgpack message"),
    (_raw([1, 2, 3]), "must be a map, got list"),
    (_raw("hello"), "must be a map, got str"),
    (_raw({"type": "health"}), "protocol version None not supported"),
    (_raw({"version": 99, "type": "health"}), "protocol version 99 not supported"),
    (_raw({"version": PROTOCOL_VERSION}), "no string 'type'"),
    (_raw({"version": PROTOCOL_VERSION, "type": 5}), "no string 'type'"),
    (_raw({"version": PROTOCOL_VERSION, "type": "x", "a": _nd(dtype="|O")}), "dtype '\\|O' not allowed"),
    (_raw({"version": PROTOCOL_VERSION, "type": "x", "a": _nd(dtype="<c16")}), "dtype '<c16' not allowed"),
    (_raw({"version": PROTOCOL_VERSION, "type": "x", "a": _nd(shape=(3,))}), "data is 8 bytes but .* need 12"),
    (_raw({"version": PROTOCOL_VERSION, "type": "x", "a": _nd(offset=4)}), "outside the payload's 8-byte tail"),
    (_raw({"version": PROTOCOL_VERSION, "type": "x", "a": _nd(offset=-1)}), "outside the payload"),
    (_raw({"version": PROTOCOL_VERSION, "type": "x", "a": _nd(shape=(-2,))}), "shape .* non-negative ints"),
    (_raw({"version": PROTOCOL_VERSION, "type": "x", "a": _nd(shape=[1] * 9)}), "at most 8"),
    (_raw({"version": PROTOCOL_VERSION, "type": "x", "a": _nd(nbytes="8")}), "outside the payload"),
    (_raw({"version": PROTOCOL_VERSION, "type": "x", "a": _nd(shape=(1 << 20, 1 << 20))}), "exceeds the bound"),
    (_raw({"version": PROTOCOL_VERSION, "type": "x", "a": _nd(shape=(1 << 32, 1 << 32))}), "exceeds the bound"),  # 2**64
    (_raw({"version": PROTOCOL_VERSION, "type": "x", "a": _nd(shape=(True, 2))}), "non-negative ints"),
    (_raw({1: "int keys", "version": PROTOCOL_VERSION, "type": "x"}), "not a valid msgpack message"),
])
def test_decode_rejects_malformed_payloads(payload, match):
    with pytest.raises(ProtocolError, match=match):
        decode(payload)


def test_decode_rejects_random_bytes():
    rng = np.random.default_rng(1)
    for _ in range(200):
        blob = rng.integers(0, 256, size=int(rng.integers(1, 64)), dtype=np.uint8).tobytes()
        with pytest.raises(ProtocolError):
            decode(blob)


def test_decode_rejects_oversize_payloads(monkeypatch):
    monkeypatch.setattr(codec, "MAX_MESSAGE_BYTES", 1024)
    with pytest.raises(ProtocolError, match="message of 2048 bytes exceeds the bound 1024"):
        decode(b"\0" * 2048)


def test_decoded_arrays_are_read_only_views():
    out = decode(encode({"type": "x", "a": np.zeros(3, np.float32)}))
    with pytest.raises(ValueError):
        out["a"][0] = 1.0


def test_decoded_arrays_view_the_payload_in_place():
    images = np.arange(4 * 64 * 64, dtype=np.float32).reshape(4, 1, 64, 64)
    payload = encode({"type": "x", "images": {"depth": images}, "n": np.arange(3)})
    out = decode(payload)
    np.testing.assert_array_equal(out["images"]["depth"], images)
    assert out["images"]["depth"].base is not None and np.shares_memory(out["images"]["depth"], np.frombuffer(payload, np.uint8))


@pytest.mark.parametrize("marker", [
    True, 1.0, 2, 0, "1", None, [1],
])
def test_only_the_exact_int_marker_makes_an_array(marker):
    """``{"__nd__": true}`` and ``1.0`` equal 1 in Python, but only the int 1 is the marker."""
    bad = {**_nd(), "__nd__": marker}
    with pytest.raises(ProtocolError, match="must be exactly an array marker"):
        decode(_raw({"version": PROTOCOL_VERSION, "type": "x", "a": bad}))


@pytest.mark.parametrize("change", ["drop_dtype", "drop_nbytes", "extra_key"])
def test_an_array_marker_has_exactly_its_five_keys(change):
    bad = _nd()
    if change == "extra_key":
        bad["note"] = "x"
    else:
        del bad[change.removeprefix("drop_")]
    with pytest.raises(ProtocolError, match="must be exactly an array marker"):
        decode(_raw({"version": PROTOCOL_VERSION, "type": "x", "a": bad}))


def test_fuzzed_array_markers_are_refused_or_decoded_exactly():
    """Mutated markers (values of every msgpack type in every field, keys dropped or added), nested
    at any depth: decode either raises ProtocolError or returns the exact array the marker names."""
    rng = np.random.default_rng(7)
    tail = np.arange(16, dtype=np.float32).tobytes()
    values = [True, False, 1, 1.0, 0, -1, 2, 8, 64, 2**63 - 1, -(2**63), "1", "<f4", "|O", "<f8", None, [], [2], [4, 4],
              [True], [2.0], {}, {"__nd__": 1}, b"\x01"]
    decoded = refused = 0
    for _ in range(3000):
        marker = _nd(shape=(int(rng.integers(0, 5)),), offset=int(rng.integers(0, 3)) * 4, nbytes=0)
        marker["nbytes"] = 4 * marker["shape"][0]
        for _ in range(int(rng.integers(0, 3))):
            op = rng.integers(0, 3)
            key = ["__nd__", "dtype", "shape", "offset", "nbytes", "extra"][int(rng.integers(0, 6))]
            if op == 0:
                marker[key] = values[int(rng.integers(0, len(values)))]
            elif op == 1:
                marker.pop(key, None)
        obj, path = marker, []
        for _ in range(int(rng.integers(0, 3))):
            obj, step = ({"nested": obj}, "nested") if rng.integers(0, 2) else ([obj], 0)
            path.insert(0, step)
        payload = _raw({"version": PROTOCOL_VERSION, "type": "x", "a": obj}, tail)
        try:
            out = decode(payload)["a"]
        except ProtocolError:
            refused += 1
            continue
        for step in path:
            out = out[step]
        if "__nd__" not in marker:  # a plain map: it stays one
            assert out == marker
            continue
        exact = (marker.keys() == {"__nd__", "dtype", "shape", "offset", "nbytes"} and type(marker["__nd__"]) is int
                 and marker["__nd__"] == 1)
        assert exact, marker
        assert isinstance(out, np.ndarray) and out.dtype == np.dtype(marker["dtype"])
        assert list(out.shape) == marker["shape"] and out.nbytes == marker["nbytes"]
        start = marker["offset"]
        assert out.tobytes() == tail[start:start + out.nbytes]
        decoded += 1
    assert decoded > 100 and refused > 100, (decoded, refused)
