"""msgpack encoding of messages, with numpy arrays as raw bytes plus dtype and shape.

A message is a msgpack map with ``version`` and ``type``. It is data, never code: no pickle, no
object hooks beyond the array form below, and every decode is validated and bounded.

Framing: ``b"VFD1"``, a little-endian ``u32`` header length, the msgpack header, then the raw bytes
of every array, back to back. An array in the header is the map ``{"__nd__": 1, "dtype": "<f4",
"shape": [n, 7], "offset": o, "nbytes": b}`` pointing into that tail, so the receiver views images in
place (an ndarray over the payload, no copy) and the sender writes each array's bytes once.
The key ``__nd__`` is reserved: a map holding it must be exactly that marker (the int ``1``, not
``true`` or ``1.0``, and those five keys, no other), or the message is refused.
"""

from __future__ import annotations

import math
import struct
from typing import Any, Mapping

import msgpack
import numpy as np

from visfly_dist.errors import ErrorCode, ProtocolError

PROTOCOL_VERSION = 3
MAX_MESSAGE_BYTES = 512 * 1024 * 1024
MAX_ARRAY_ELEMENTS = 256 * 1024 * 1024
ALLOWED_DTYPES = frozenset(
    np.dtype(t).str for t in ("bool", "uint8", "uint16", "int32", "int64", "float32", "float64")
)
_DTYPES = {name: np.dtype(name) for name in ALLOWED_DTYPES}
_ND = "__nd__"
_ND_KEYS = frozenset({_ND, "dtype", "shape", "offset", "nbytes"})
MAGIC = b"VFD1"
_PREFIX = struct.Struct("<4sI")


class _Tail:
    """The arrays of one message being encoded, in the order they will follow the header."""

    def __init__(self) -> None:
        self.buffers: list[Any] = []  # C-contiguous arrays: ``bytes.join`` takes their bytes as they are
        self.size = 0

    def default(self, obj: Any) -> Any:
        if isinstance(obj, np.ndarray):
            arr = obj if obj.flags.c_contiguous else np.ascontiguousarray(obj)  # ascontiguousarray makes 0-d arrays 1-d
            dtype = arr.dtype.str
            if dtype not in ALLOWED_DTYPES:
                raise ProtocolError(f"array dtype {arr.dtype} cannot travel; allowed: {sorted(ALLOWED_DTYPES)}")
            ref = {_ND: 1, "dtype": dtype, "shape": arr.shape, "offset": self.size, "nbytes": arr.nbytes}  # a tuple packs as a list
            self.buffers.append(arr)
            self.size += arr.nbytes
            return ref
        if isinstance(obj, np.generic):
            return obj.item()
        if isinstance(obj, tuple):
            return list(obj)
        raise ProtocolError(f"cannot encode {type(obj).__name__}: messages carry only plain data and numpy arrays")


def _array_hook(payload: bytes, tail_start: int):
    """The msgpack object hook that turns array references into read-only views on ``payload``."""
    tail_size = len(payload) - tail_start

    def hook(d: dict) -> Any:
        if _ND not in d:
            return d
        if type(d[_ND]) is not int or d[_ND] != 1 or d.keys() != _ND_KEYS:  # True == 1 and 1.0 == 1: refused
            raise ProtocolError(f"a map holding {_ND!r} must be exactly an array marker {{{_ND!r}: 1, 'dtype', "
                                f"'shape', 'offset', 'nbytes'}}; got keys {sorted(map(str, d))} with {_ND!r}: "
                                f"{d[_ND]!r}")
        dtype, shape, offset, nbytes = d["dtype"], d["shape"], d["offset"], d["nbytes"]
        dt = _DTYPES.get(dtype) if isinstance(dtype, str) else None
        if dt is None:
            raise ProtocolError(f"array dtype {dtype!r} not allowed; allowed: {sorted(ALLOWED_DTYPES)}")
        if not isinstance(shape, list) or len(shape) > 8:
            raise ProtocolError(f"array shape {shape!r} must be a list of at most 8 non-negative ints")
        for s in shape:  # a loop, not all(...): no generator per array
            if type(s) is not int or s < 0:
                raise ProtocolError(f"array shape {shape!r} must be a list of at most 8 non-negative ints")
        if type(offset) is not int or type(nbytes) is not int or offset < 0 or nbytes < 0 \
                or offset + nbytes > tail_size:
            raise ProtocolError(f"array bytes [{offset!r}, +{nbytes!r}) lie outside the payload's {tail_size}-byte tail")
        count = math.prod(shape)  # Python ints: no overflow, and no NumPy call per array
        if count > MAX_ARRAY_ELEMENTS:
            raise ProtocolError(f"array of {count} elements exceeds the bound {MAX_ARRAY_ELEMENTS}")
        if count * dt.itemsize != nbytes:
            raise ProtocolError(f"array data is {nbytes} bytes but dtype {dtype} and shape {shape} need {count * dt.itemsize}")
        return np.ndarray(shape, dt, payload, tail_start + offset)  # one call; read-only, as the payload is bytes

    return hook


def encode(message: Mapping[str, Any]) -> bytes:
    """Encode a message map (must hold ``type``); adds the protocol ``version``.

    Each array's bytes are copied once, into the returned payload.
    """
    if "type" not in message:
        raise ProtocolError("a message needs a 'type'")
    tail = _Tail()
    header = msgpack.packb({"version": PROTOCOL_VERSION, **message}, default=tail.default, use_bin_type=True)
    return b"".join([_PREFIX.pack(MAGIC, len(header)), header, *tail.buffers])


def decode(payload: bytes | bytearray | memoryview) -> dict[str, Any]:
    """Decode and check the envelope of a message; raises ProtocolError on anything malformed.

    Arrays come back read-only views on the payload (no copy); copy before writing to them.
    """
    if len(payload) > MAX_MESSAGE_BYTES:
        raise ProtocolError(f"message of {len(payload)} bytes exceeds the bound {MAX_MESSAGE_BYTES}")
    payload = payload if isinstance(payload, bytes) else bytes(payload)
    if len(payload) < _PREFIX.size or payload[:4] != MAGIC:
        raise ProtocolError(f"payload does not start with the framing {MAGIC!r} + header length")
    _, header_len = _PREFIX.unpack_from(payload)
    tail_start = _PREFIX.size + header_len
    if tail_start > len(payload):
        raise ProtocolError(f"header length {header_len} exceeds the {len(payload)}-byte payload")
    try:
        msg = msgpack.unpackb(
            memoryview(payload)[_PREFIX.size:tail_start], object_hook=_array_hook(payload, tail_start), raw=False,
            strict_map_key=True, max_bin_len=MAX_MESSAGE_BYTES, max_str_len=16 * 1024 * 1024,
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
