r"""The worker's side of image segments: open the learner's sealed memfd, prove it is the learner's,
and write a step's images into it (:mod:`visfly_dist.protocol.image_segment`).

The worker opens the segment through the learner's descriptor (``/proc/<pid>/fd/<fd>``, two ints
from the request: nothing else is ever opened), and uses it only if it is a memfd sealed against
shrinking and growing and holds the request's nonce. The worker never maps a segment: it renders
into buffers of its own and ``pwrite``\ s each entry's rows into it (measured on a 2-core host: 4 MiB
of depth images, 2.7 ms against 0.3 ms for stores into a mapping; a ``visfly-dist bench step`` of
256 agents at 64x64, one raycast worker, did not tell the two apart: a median of 956 against 957
env-steps/s over 5 interleaved runs each).

Segments are cached by name (an open descriptor each): the learner may close its descriptor once
it retires a segment, and this worker keeps writing where its own descriptor points. The cache
keeps the few most recently used and closes older ones (a learner grows a segment by making a new
one).
"""

from __future__ import annotations

import fcntl
import os
from collections import OrderedDict
from typing import Sequence

import numpy as np

from visfly_dist.errors import ProtocolError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.image_segment import (
    NONCE_BYTES,
    SEALS,
    SEQ,
    SegmentTarget,
    block_bytes,
)

MAX_MAPPINGS = 8


class SegmentMappings:
    """Segments this worker has open, by name (most recently used last), and its image buffers."""

    def __init__(self, max_mappings: int = MAX_MAPPINGS) -> None:
        self._files: OrderedDict[str, tuple[int, int]] = OrderedDict()  # name -> (fd, size)
        self._max = max_mappings
        self._buffers: dict[tuple[str, str, tuple[int, ...]], np.ndarray] = {}

    def views(self, target: SegmentTarget, cameras: Sequence[CameraSpec],
              rows: int) -> tuple[dict[str, np.ndarray] | None, str]:
        """Writable ``(rows, C, H, W)`` buffers of each camera and ``""``; or ``None`` and why the
        segment cannot be used (nothing to open, not a sealed memfd, another nonce in it: not the
        learner's host or pid namespace). Render into the buffers, then :meth:`publish` writes them.

        Marks the segment's images as being written (sequence number 0 at the target's
        ``seq_offset``) until :meth:`publish`.

        Raises:
            ProtocolError: blocks that do not fit the cameras or the segment, or a segment whose size
                differs from the request's.
        """
        target.check_blocks({c.name: block_bytes(c, rows) for c in cameras})
        entry = self._files.get(target.name)
        if entry is not None and entry[1] != target.size:
            raise ProtocolError(f"image segment {target.name!r} was opened with {entry[1]} bytes; the request "
                                f"says {target.size}")
        if entry is None:
            fd, why = self._open(target)
            if fd is None:
                return None, why
            entry = (fd, target.size)
        fd = entry[0]
        try:
            if os.pread(fd, NONCE_BYTES, 0) != target.nonce:
                self._drop(target.name, entry)
                return None, (f"image segment {target.name!r} holds another nonce (a different host or pid "
                              "namespace)")
            self._files[target.name] = entry
            self._files.move_to_end(target.name)
            while len(self._files) > self._max:
                os.close(self._files.popitem(last=False)[1][0])
            os.pwrite(fd, SEQ.pack(0), target.seq_offset)
        except OSError as exc:
            self._drop(target.name, entry)
            return None, f"image segment {target.name!r} cannot be written: {exc.strerror}"
        return {c.name: self._buffer(target.name, c, rows) for c in cameras}, ""

    def publish(self, target: SegmentTarget, images: dict[str, np.ndarray], starts: np.ndarray,
                counts: np.ndarray) -> str:
        """Write each entry's rows of ``images`` into the segment, then its sequence number into the
        header; ``""``, or why the segment could not take them (the caller replies inline then)."""
        fd, size = self._files[target.name]
        try:
            for name, block in target.blocks.items():
                image = images[name]
                row_bytes = image[0].nbytes if len(image) else 0
                for start, count in zip(starts.tolist(), counts.tolist()):
                    if count:
                        _pwrite_all(fd, image[start:start + count].data.cast("B"), block + start * row_bytes)
            os.pwrite(fd, SEQ.pack(target.seq), target.seq_offset)
        except OSError as exc:
            self._drop(target.name, (fd, size))
            return f"image segment {target.name!r} cannot be written: {exc.strerror}"
        return ""

    def _buffer(self, name: str, camera: CameraSpec, rows: int) -> np.ndarray:
        """A reused ``(rows, C, H, W)`` buffer of ``camera``'s images (grown to the next power of two)."""
        key = (camera.name, camera.dtype.str, tuple(camera.shape))
        buf = self._buffers.get(key)
        if buf is None or len(buf) < rows:
            buf = self._buffers[key] = np.empty((1 << max(rows - 1, 0).bit_length(), *camera.shape), camera.dtype)
        return buf[:rows]

    def _drop(self, name: str, entry: tuple[int, int]) -> None:
        if self._files.get(name) == entry:
            del self._files[name]
        os.close(entry[0])

    @staticmethod
    def _open(target: SegmentTarget) -> tuple[int | None, str]:
        """The segment's descriptor and ``""``, or None and why it cannot be used.

        Opened without blocking and never as a controlling terminal, whatever the descriptor there
        is; used only if it is a memfd with the segment's seals (nobody can resize it) and the
        request's nonce (another host's or pid namespace's process has other descriptors there);
        then its size must be the request's.
        """
        path = target.path()
        try:
            fd = os.open(path, os.O_RDWR | os.O_CLOEXEC | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError as exc:
            return None, f"cannot open image segment {target.name!r} at {path}: {exc.strerror}"
        try:
            try:
                seals = fcntl.fcntl(fd, fcntl.F_GET_SEALS)
            except OSError:
                seals = 0
            if seals & SEALS != SEALS or os.pread(fd, NONCE_BYTES, 0) != target.nonce:
                os.close(fd)
                return None, (f"{path} is not image segment {target.name!r} (another host, or another pid "
                              "namespace)")
            size = os.fstat(fd).st_size
            if size != target.size:
                raise ProtocolError(f"image segment {target.name!r} has {size} bytes; the request says {target.size}")
        except BaseException:
            os.close(fd)
            raise
        return fd, ""

    def close(self) -> None:
        """Close every segment file and free the buffers (idempotent)."""
        while self._files:
            os.close(self._files.popitem()[1][0])
        self._buffers.clear()

    def names(self) -> dict[str, int]:
        """Open segment names -> sizes (for the health reply)."""
        return {name: size for name, (_, size) in self._files.items()}


def _pwrite_all(fd: int, data: memoryview, offset: int) -> None:
    while len(data):
        done = os.pwrite(fd, data, offset)
        data, offset = data[done:], offset + done
