"""msgpack encoding of messages, with numpy arrays as raw bytes plus dtype and shape.

A message is a msgpack map with ``version`` and ``type``. It is data, never code: no pickle, no
object hooks beyond the array form below, and every decode is validated and bounded.

Array form (a nested map): ``{"__nd__": 1, "dtype": "<f4", "shape": [n, 7], "data": <bytes>}``.
"""

from __future__ import annotations

from typing import Any, Mapping

import msgpack
import numpy as np

from visfly_dist.errors import ErrorCode, ProtocolError

PROTOCOL_VERSION = 1
MAX_MESSAGE_BYTES = 512 * 1024 * 1024
MAX_ARRAY_ELEMENTS = 256 * 1024 * 1024
ALLOWED_DTYPES = frozenset(
    np.dtype(t).str for t in ("bool", "uint8", "uint16", "int32", "int64", "float32", "float64")
)
_ND = "__nd__"


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        arr = obj if obj.flags.c_contiguous else np.ascontiguousarray(obj)  # ascontiguousarray makes 0-d arrays 1-d
        if arr.dtype.str not in ALLOWED_DTYPES:
            raise ProtocolError(f"array dtype {arr.dtype} cannot travel; allowed: {sorted(ALLOWED_DTYPES)}")
        return {_ND: 1, "dtype": arr.dtype.str, "shape": list(arr.shape), "data": arr.tobytes()}
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, tuple):
        return list(obj)
    raise ProtocolError(f"cannot encode {type(obj).__name__}: messages carry only plain data and numpy arrays")


def _object_hook(d: dict) -> Any:
    if d.get(_ND) != 1:
        return d
    dtype, shape, data = d.get("dtype"), d.get("shape"), d.get("data")
    if not isinstance(dtype, str) or dtype not in ALLOWED_DTYPES:
        raise ProtocolError(f"array dtype {dtype!r} not allowed; allowed: {sorted(ALLOWED_DTYPES)}")
    if (not isinstance(shape, list) or len(shape) > 8
            or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape)):
        raise ProtocolError(f"array shape {shape!r} must be a list of at most 8 non-negative ints")
    if not isinstance(data, (bytes, bytearray)):
        raise ProtocolError("array data must be bytes")
    count = int(np.prod(shape, dtype=np.int64)) if shape else 1
    if count > MAX_ARRAY_ELEMENTS:
        raise ProtocolError(f"array of {count} elements exceeds the bound {MAX_ARRAY_ELEMENTS}")
    dt = np.dtype(dtype)
    if count * dt.itemsize != len(data):
        raise ProtocolError(f"array data is {len(data)} bytes but dtype {dtype} and shape {shape} need {count * dt.itemsize}")
    return np.frombuffer(data, dtype=dt).reshape(shape)


def encode(message: Mapping[str, Any]) -> bytes:
    """Encode a message map (must hold ``type``); adds the protocol ``version``."""
    if "type" not in message:
        raise ProtocolError("a message needs a 'type'")
    body = {"version": PROTOCOL_VERSION, **message}
    return msgpack.packb(body, default=_default, use_bin_type=True)


def decode(payload: bytes | bytearray | memoryview) -> dict[str, Any]:
    """Decode and check the envelope of a message; raises ProtocolError on anything malformed.

    Arrays come back read-only (views on the payload); copy before writing to them.
    """
    if len(payload) > MAX_MESSAGE_BYTES:
        raise ProtocolError(f"message of {len(payload)} bytes exceeds the bound {MAX_MESSAGE_BYTES}")
    try:
        msg = msgpack.unpackb(
            bytes(payload), object_hook=_object_hook, raw=False, strict_map_key=True,
            max_bin_len=MAX_MESSAGE_BYTES, max_str_len=16 * 1024 * 1024,
        )
    except ProtocolError:
        raise
    except Exception as exc:  # msgpack raises many types on garbage
        raise ProtocolError(f"payload is not a valid msgpack message: {type(exc).__name__}: {exc}") from None
    if not isinstance(msg, dict):
        raise ProtocolError(f"a message must be a map, got {type(msg).__name__}")
    version = msg.get("version")
    if type(version) is not int or version != PROTOCOL_VERSION:  # True == 1 and 1.0 == 1 are refused
        raise ProtocolError(f"protocol version {version!r} not supported; this side speaks {PROTOCOL_VERSION}")
    if not isinstance(msg.get("type"), str):
        raise ProtocolError("message has no string 'type'")
    return msg


def error_message(error_type: str, code: ErrorCode, message: str) -> bytes:
    """An encoded error reply (sent with ``reply_err``): ``{"type": "error", "error": error_type,
    "code": code, "message": message}``; ``code`` is one of :class:`~visfly_dist.errors.ErrorCode`."""
    return encode({"type": "error", "error": error_type, "code": ErrorCode(code).value, "message": message})
