"""The worker's side of image segments: map the learner's ``/dev/shm`` file, prove it is the learner's,
and give the renderer numpy views to write into (:mod:`visfly_dist.protocol.image_segment`).

Mappings are cached by name: the learner unlinks a file as soon as this worker has answered a
request that used it, so later requests find the mapping here, not the file. The cache keeps the
few most recently used mappings and closes older ones (a learner grows a segment by naming a new
file).
"""

from __future__ import annotations

import mmap
import os
import stat
from collections import OrderedDict
from typing import Sequence

import numpy as np

from visfly_dist.errors import ProtocolError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.image_segment import (
    NONCE_BYTES, SEQ, SHM_DIR, SegmentTarget, block_bytes, block_view,
)

MAX_MAPPINGS = 8


class SegmentMappings:
    """Segments this worker has mapped, by name (most recently used last)."""

    def __init__(self, max_mappings: int = MAX_MAPPINGS) -> None:
        self._maps: OrderedDict[str, mmap.mmap] = OrderedDict()
        self._max = max_mappings

    def views(self, target: SegmentTarget, cameras: Sequence[CameraSpec],
              rows: int) -> tuple[dict[str, np.ndarray] | None, str]:
        """Writable ``(rows, C, H, W)`` views of each camera's block and ``""``; or ``None`` and why the
        segment cannot be used (no such file here, or another nonce in it: not the learner's host).

        Marks the segment's images as being written (sequence number 0 at the target's
        ``seq_offset``) until :meth:`publish`.

        Raises:
            ProtocolError: blocks that do not fit the cameras or the segment, or a file whose size
                differs from the request's.
        """
        target.check_blocks({c.name: block_bytes(c, rows) for c in cameras})
        mm = self._maps.get(target.name)
        if mm is not None and len(mm) != target.size:
            raise ProtocolError(f"image segment {target.name!r} is mapped with {len(mm)} bytes; the request "
                                f"says {target.size}")
        if mm is None:
            mm, why = self._open(target)
            if mm is None:
                return None, why
        if mm[:NONCE_BYTES] != target.nonce:
            _close(self._maps.pop(target.name, mm))
            return None, f"image segment {target.name!r} holds another nonce (a different host or /dev/shm)"
        self._maps[target.name] = mm
        self._maps.move_to_end(target.name)
        while len(self._maps) > self._max:
            _close(self._maps.popitem(last=False)[1])
        SEQ.pack_into(mm, target.seq_offset, 0)
        return {c.name: block_view(mm, target.blocks[c.name], c, rows) for c in cameras}, ""

    def publish(self, target: SegmentTarget) -> None:
        """Mark ``target``'s images complete: its sequence number goes into the header."""
        SEQ.pack_into(self._maps[target.name], target.seq_offset, target.seq)

    @staticmethod
    def _open(target: SegmentTarget) -> tuple[mmap.mmap | None, str]:
        path = os.path.join(SHM_DIR, target.name)  # the name holds no separator and no dot (check_name)
        try:
            fd = os.open(path, os.O_RDWR | os.O_NOFOLLOW | os.O_CLOEXEC)
        except OSError as exc:
            return None, f"cannot open image segment {path}: {exc.strerror}"
        try:
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode):
                raise ProtocolError(f"image segment {path} is not a regular file")
            if st.st_size != target.size:
                raise ProtocolError(f"image segment {path} has {st.st_size} bytes; the request says {target.size}")
            return mmap.mmap(fd, target.size), ""
        finally:
            os.close(fd)

    def close(self) -> None:
        """Unmap every segment (idempotent)."""
        while self._maps:
            _close(self._maps.popitem()[1])

    def names(self) -> dict[str, int]:
        """Mapped segment names -> sizes (for the health reply)."""
        return {name: len(mm) for name, mm in self._maps.items()}


def _close(mm: mmap.mmap) -> None:
    try:
        mm.close()
    except BufferError:  # a view of it still exists: the mapping goes with the last view
        pass
