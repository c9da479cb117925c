"""The image segment: a ``/dev/shm`` file through which a worker on the learner's host hands over images.

The learner creates the file (mode 0600), writes a random nonce at its start, and names it in a
step request (:class:`SegmentTarget`, the request's ``image_segment`` field) together with where
each camera's block of images lies. A worker that can open the file and reads the same nonce
there is on the learner's host and sees the same ``/dev/shm``: it writes the images into the
blocks, then the request's sequence number into the header, and replies with the query arrays
only and ``images_in_segment: true``. Otherwise it replies inline as without a segment, with
``segment_refused`` giving the reason. Both sides share this module; neither imports the other.

Layout (little-endian)::

    [0, 16)    nonce, written once by the learner
    [16, 24)   u64 sequence number of the last request whose images are complete (0: being written)
    [64, ...)  camera blocks, each (rows, C, H, W) of the camera's dtype, C-contiguous
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from visfly_dist.errors import ProtocolError
from visfly_dist.protocol.cameras import CameraSpec

SHM_DIR = "/dev/shm"
NAME_PREFIX = "visfly-img-"
MAX_NAME_CHARS = 200
NONCE_BYTES = 16
SEQ_OFFSET = 16
SEQ = struct.Struct("<Q")
HEADER_BYTES = 64
BLOCK_ALIGN = 64
MAX_SEGMENT_BYTES = 1 << 36
MAX_SEQ = 2**63 - 1
_NAME = re.compile(r"[A-Za-z0-9_-]+")


def check_name(name: Any) -> str:
    """``name`` if it is a safe segment file name (no path, no dots), else ProtocolError."""
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
    return rows * int(np.prod(camera.shape)) * camera.dtype.itemsize


def layout(cameras: Sequence[CameraSpec], rows: int) -> tuple[dict[str, int], int]:
    """Block offsets for ``rows`` images of each camera (aligned, after the header), and the bytes needed."""
    blocks, end = {}, HEADER_BYTES
    for cam in cameras:
        blocks[cam.name] = end
        end = align(end + block_bytes(cam, rows))
    return blocks, end


def block_view(buffer: Any, offset: int, camera: CameraSpec, rows: int) -> np.ndarray:
    """The ``(rows, C, H, W)`` array of ``camera``'s block at ``offset`` of ``buffer`` (no copy)."""
    count = rows * int(np.prod(camera.shape))
    return np.frombuffer(buffer, camera.dtype, count, offset).reshape(rows, *camera.shape)


@dataclass(frozen=True)
class SegmentTarget:
    """Where a step request wants its images: segment file, nonce, size, sequence number, blocks.

    Attributes:
        name: the file's name in ``/dev/shm`` (:func:`check_name`).
        nonce: the :data:`NONCE_BYTES` bytes the learner wrote at the file's start.
        size: the file's size in bytes.
        seq: this request's sequence number (>= 1), written by the worker once the images are in.
        blocks: camera name -> byte offset of its ``(rows, C, H, W)`` block.
    """

    name: str
    nonce: bytes
    size: int
    seq: int
    blocks: dict[str, int]

    def to_message(self) -> dict[str, Any]:
        return {"name": self.name, "nonce": self.nonce, "size": self.size, "seq": self.seq, "blocks": self.blocks}

    @classmethod
    def parse(cls, msg: Any) -> "SegmentTarget":
        """Validate the request's ``image_segment`` map; ProtocolError naming what is wrong."""
        what = "step.image_segment"
        if not isinstance(msg, Mapping) or set(msg) != {"name", "nonce", "size", "seq", "blocks"}:
            got = sorted(map(str, msg)) if isinstance(msg, Mapping) else type(msg).__name__
            raise ProtocolError(f"{what} must be a map of name, nonce, size, seq, blocks; got {got}")
        name = check_name(msg["name"])
        nonce, size, seq, blocks = msg["nonce"], msg["size"], msg["seq"], msg["blocks"]
        if not isinstance(nonce, bytes) or len(nonce) != NONCE_BYTES:
            raise ProtocolError(f"{what}.nonce must be {NONCE_BYTES} bytes")
        if type(size) is not int or not HEADER_BYTES <= size <= MAX_SEGMENT_BYTES:
            raise ProtocolError(f"{what}.size={size!r} must be an int in [{HEADER_BYTES}, {MAX_SEGMENT_BYTES}]")
        if type(seq) is not int or not 1 <= seq <= MAX_SEQ:
            raise ProtocolError(f"{what}.seq={seq!r} must be an int in [1, 2**63 - 1]")
        if not isinstance(blocks, Mapping) or not all(
                isinstance(k, str) and type(v) is int and HEADER_BYTES <= v < size for k, v in blocks.items()):
            raise ProtocolError(f"{what}.blocks must map camera names to int offsets in [{HEADER_BYTES}, {size})")
        return cls(name, nonce, size, seq, dict(blocks))

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
