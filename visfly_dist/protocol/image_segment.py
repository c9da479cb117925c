"""The image segment: a sealed memfd through which a worker on the learner's host hands over images.

The learner creates the segment (``memfd_create``, sealed against shrinking and growing, so no
process can truncate it under a mapping), writes a random nonce at its start, and names it in a
step request (:class:`SegmentTarget`, the request's ``image_segment`` field) together with where
each camera's block of images lies. The worker opens it through the learner's descriptor
(``/proc/<pid>/fd/<fd>``): one that can, and reads the same nonce there, is on the learner's host
in its pid namespace. It writes the images into the blocks, then the request's sequence number
into the header, and replies with the query arrays only and ``images_in_segment: true``.
Otherwise it replies inline as without a segment, with ``segment_refused`` giving the reason.
Both sides share this module; neither imports the other.

Layout (little-endian)::

    [0, 16)    nonce, written once by the learner
    [16, 24)   u64 sequence number of the last request whose images are complete (0: being written)
    [64, ...)  camera blocks, each (rows, C, H, W) of the camera's dtype, C-contiguous
"""

from __future__ import annotations

import fcntl
import math
import re
import struct
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from visfly_dist.errors import ProtocolError
from visfly_dist.protocol.cameras import CameraSpec

NAME_PREFIX = "visfly-img-"
MAX_NAME_CHARS = 200
NONCE_BYTES = 16
SEQ_OFFSET = 16
SEQ = struct.Struct("<Q")
HEADER_BYTES = 64
BLOCK_ALIGN = 64
MAX_SEGMENT_BYTES = 1 << 36
MAX_SEQ = 2**63 - 1
MAX_PID = 2**22
"""Linux's largest pid (``PID_MAX_LIMIT``)."""
MAX_FD = 2**31 - 1
SEALS = fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_GROW | fcntl.F_SEAL_SEAL
"""The seals of every segment: its size is fixed, and nobody can add a seal (a write seal would
make the workers' writes fail)."""
_NAME = re.compile(r"[A-Za-z0-9_-]+")


def check_name(name: Any) -> str:
    """``name`` if it is a safe segment name (no path, no dots), else ProtocolError."""
    if not isinstance(name, str) or len(name) > MAX_NAME_CHARS or not name.startswith(NAME_PREFIX) \
            or not _NAME.fullmatch(name):
        shown = name if not isinstance(name, str) or len(name) <= 80 else name[:80] + "..."
        raise ProtocolError(f"image_segment name {shown!r} must be {NAME_PREFIX!r} followed by letters, digits, "
                            f"'_' or '-', at most {MAX_NAME_CHARS} chars (no path separators, no dots)")
    return name


def align(n: int) -> int:
    """``n`` rounded up to :data:`BLOCK_ALIGN`."""
    return -(-n // BLOCK_ALIGN) * BLOCK_ALIGN


def block_bytes(camera: CameraSpec, rows: int) -> int:
    """Bytes of ``rows`` images of ``camera``."""
    return rows * math.prod(camera.shape) * camera.dtype.itemsize


def layout(cameras: Sequence[CameraSpec], rows: int) -> tuple[dict[str, int], int]:
    """Block offsets for ``rows`` images of each camera (aligned, after the header), and the bytes needed."""
    blocks, end = {}, HEADER_BYTES
    for cam in cameras:
        blocks[cam.name] = end
        end = align(end + block_bytes(cam, rows))
    return blocks, end


def block_view(buffer: Any, offset: int, camera: CameraSpec, rows: int) -> np.ndarray:
    """The ``(rows, C, H, W)`` array of ``camera``'s block at ``offset`` of ``buffer`` (no copy)."""
    count = rows * math.prod(camera.shape)
    return np.frombuffer(buffer, camera.dtype, count, offset).reshape(rows, *camera.shape)


@dataclass(frozen=True)
class SegmentTarget:
    """Where a step request wants its images: segment, nonce, size, sequence number, blocks.

    Attributes:
        name: the segment's name (:func:`check_name`): what the worker caches it by, and the memfd's
            name (``/memfd:<name>`` in ``/proc``).
        nonce: the :data:`NONCE_BYTES` bytes the learner wrote at the segment's start.
        size: the segment's size in bytes.
        seq: this request's sequence number (>= 1), written by the worker once the images are in.
        blocks: camera name -> byte offset of its ``(rows, C, H, W)`` block.
        seq_offset: where the worker writes ``seq`` (8 bytes, before every block): several workers
            can write one segment, each its own number (default :data:`SEQ_OFFSET`).
        entry_rows: the block row of each request entry's first image (default: the entries one
            after another from row 0); lets the learner lay a step's images out in observation order.
        pid: the learner's process id, and
        fd: its descriptor of the segment: a worker opens ``/proc/<pid>/fd/<fd>`` (:meth:`path`).
    """

    name: str
    nonce: bytes
    size: int
    seq: int
    blocks: dict[str, int]
    pid: int
    fd: int
    seq_offset: int = SEQ_OFFSET
    entry_rows: tuple[int, ...] | np.ndarray | None = None  # the learner's int64 array, parsed as a tuple

    def path(self) -> str:
        """Where a worker on the learner's host opens the segment (two ints: nothing else is reachable)."""
        return f"/proc/{self.pid}/fd/{self.fd}"

    def to_message(self) -> dict[str, Any]:
        msg: dict[str, Any] = {"name": self.name, "nonce": self.nonce, "size": self.size, "seq": self.seq,
                               "blocks": self.blocks, "pid": self.pid, "fd": self.fd}
        if self.seq_offset != SEQ_OFFSET:
            msg["seq_offset"] = self.seq_offset
        if self.entry_rows is not None:
            msg["entry_rows"] = np.asarray(self.entry_rows, dtype=np.int64)
        return msg

    @classmethod
    def parse(cls, msg: Any) -> "SegmentTarget":
        """Validate the request's ``image_segment`` map; ProtocolError naming what is wrong."""
        what = "step.image_segment"
        required, optional = {"name", "nonce", "size", "seq", "blocks", "pid", "fd"}, {"seq_offset", "entry_rows"}
        if not isinstance(msg, Mapping) or not required <= set(msg) <= required | optional:
            got = sorted(map(str, msg)) if isinstance(msg, Mapping) else type(msg).__name__
            raise ProtocolError(f"{what} must be a map of name, nonce, size, seq, blocks, pid, fd (and optionally "
                                f"seq_offset, entry_rows); got {got}")
        name = check_name(msg["name"])
        nonce, size, seq, blocks = msg["nonce"], msg["size"], msg["seq"], msg["blocks"]
        if not isinstance(nonce, bytes) or len(nonce) != NONCE_BYTES:
            raise ProtocolError(f"{what}.nonce must be {NONCE_BYTES} bytes")
        if type(size) is not int or not HEADER_BYTES <= size <= MAX_SEGMENT_BYTES:
            raise ProtocolError(f"{what}.size={size!r} must be an int in [{HEADER_BYTES}, {MAX_SEGMENT_BYTES}]")
        if type(seq) is not int or not 1 <= seq <= MAX_SEQ:
            raise ProtocolError(f"{what}.seq={seq!r} must be an int in [1, 2**63 - 1]")
        pid, fd = msg["pid"], msg["fd"]
        if type(pid) is not int or not 1 <= pid <= MAX_PID:
            raise ProtocolError(f"{what}.pid={pid!r} must be an int in [1, {MAX_PID}]")
        if type(fd) is not int or not 0 <= fd <= MAX_FD:
            raise ProtocolError(f"{what}.fd={fd!r} must be an int in [0, {MAX_FD}]")
        if not isinstance(blocks, Mapping) or not blocks or not all(
                isinstance(k, str) and type(v) is int and HEADER_BYTES <= v < size for k, v in blocks.items()):
            raise ProtocolError(f"{what}.blocks must map camera names to int offsets in [{HEADER_BYTES}, {size})")
        seq_offset = msg.get("seq_offset", SEQ_OFFSET)
        if type(seq_offset) is not int or seq_offset % SEQ.size or not SEQ_OFFSET <= seq_offset \
                or seq_offset + SEQ.size > min(blocks.values()):
            raise ProtocolError(f"{what}.seq_offset={seq_offset!r} must be a multiple of {SEQ.size} in "
                                f"[{SEQ_OFFSET}, first block - {SEQ.size}]")
        return cls(name, nonce, size, seq, dict(blocks), pid, fd, seq_offset, _entry_rows(msg.get("entry_rows")))

    def starts(self, counts: np.ndarray) -> np.ndarray:
        """The block row of each entry's first image, checked against the entries' ``counts``."""
        counts = np.asarray(counts, dtype=np.int64)
        if self.entry_rows is None:
            return np.cumsum(counts) - counts
        if len(self.entry_rows) != len(counts):
            raise ProtocolError(f"step.image_segment.entry_rows has {len(self.entry_rows)} rows for "
                                f"{len(counts)} scene entries")
        return np.asarray(self.entry_rows, dtype=np.int64)

    def check_blocks(self, nbytes: Mapping[str, int]) -> None:
        """ProtocolError unless every camera of ``nbytes`` (name -> block bytes) has a block inside the
        segment, past the header, overlapping no other."""
        if set(self.blocks) != set(nbytes):
            raise ProtocolError(f"step.image_segment.blocks names cameras {sorted(self.blocks)}; this scene's "
                                f"cameras are {sorted(nbytes)}")
        spans = sorted((self.blocks[c], self.blocks[c] + n, c) for c, n in nbytes.items())
        end_before = HEADER_BYTES
        for start, end, cam in spans:
            if start < end_before or end > self.size:
                raise ProtocolError(f"step.image_segment block of camera {cam!r} [{start}, {end}) overlaps the "
                                    f"header or another block, or ends past the segment's {self.size} bytes")
            end_before = end


def _entry_rows(value: Any) -> tuple[int, ...] | None:
    if value is None:
        return None
    rows = np.asarray(value)
    if rows.ndim != 1 or not (rows.dtype.kind in "iu" or rows.size == 0) or (rows.size and rows.min() < 0) \
            or (rows.size and rows.max() > MAX_SEGMENT_BYTES):
        raise ProtocolError("step.image_segment.entry_rows must be a 1-D array of row indices >= 0")
    return tuple(rows.tolist())
