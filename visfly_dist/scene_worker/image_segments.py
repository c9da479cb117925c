r"""The worker's side of image segments: open the learner's ``/dev/shm`` file, prove it is the learner's,
and write a step's images into it (:mod:`visfly_dist.protocol.image_segment`).

The worker never maps a segment: it renders into buffers of its own and ``pwrite``\ s each entry's
rows into the file. Any process of the user may truncate a ``/dev/shm`` file, and a store into a
mapping past the file's new end kills the writer with SIGBUS; ``pwrite`` past the end only extends
the file again. A segment whose size is no longer the request's is refused (the images go inline,
``segment_refused`` says why), so a truncated segment costs one inline reply, never the worker. The
price: the renderer writes into a reused buffer, and ``pwrite`` copies it into the file's pages,
which costs more than stores into a mapping (measured on a 2-core host: 4 MiB of depth images,
2.7 ms against 0.3 ms). A ``visfly-dist bench step`` of 256 agents at 64x64 (one raycast worker)
did not tell the two apart: a median of 956 against 957 env-steps/s over 5 interleaved runs each.

Files are cached by name (an open descriptor each): the learner unlinks a file as soon as this worker
has answered a request that used it, so later requests find the descriptor here, not the file. The
cache keeps the few most recently used and closes older ones (a learner grows a segment by naming a
new file).
"""

from __future__ import annotations

import os
import stat
from collections import OrderedDict
from typing import Sequence

import numpy as np

from visfly_dist.errors import ProtocolError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.image_segment import (
    NONCE_BYTES,
    SEQ,
    SHM_DIR,
    SegmentTarget,
    block_bytes,
)

MAX_MAPPINGS = 8


class SegmentMappings:
    """Segment files this worker has open, by name (most recently used last), and its image buffers."""

    def __init__(self, max_mappings: int = MAX_MAPPINGS) -> None:
        self._files: OrderedDict[str, tuple[int, int]] = OrderedDict()  # name -> (fd, size)
        self._max = max_mappings
        self._buffers: dict[tuple[str, str, tuple[int, ...]], np.ndarray] = {}

    def views(self, target: SegmentTarget, cameras: Sequence[CameraSpec],
              rows: int) -> tuple[dict[str, np.ndarray] | None, str]:
        """Writable ``(rows, C, H, W)`` buffers of each camera and ``""``; or ``None`` and why the
        segment cannot be used (no such file here, another nonce in it: not the learner's host; or
        a size that changed). Render into the buffers, then :meth:`publish` writes them.

        Marks the segment's images as being written (sequence number 0 at the target's
        ``seq_offset``) until :meth:`publish`.

        Raises:
            ProtocolError: blocks that do not fit the cameras or the segment, or a file whose size
                differs from the request's when it is first opened.
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
            size = os.fstat(fd).st_size
            if size != target.size:
                self._drop(target.name, entry)
                return None, (f"image segment {target.name!r} has {size} bytes now, not {target.size}: "
                              "another process truncated or grew it")
            if os.pread(fd, NONCE_BYTES, 0) != target.nonce:
                self._drop(target.name, entry)
                return None, f"image segment {target.name!r} holds another nonce (a different host or /dev/shm)"
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
            if os.fstat(fd).st_size != size:
                self._drop(target.name, (fd, size))
                return (f"image segment {target.name!r} was truncated or grown by another process while the "
                        "images were rendered")
            for name, block in target.blocks.items():
                image = images[name]
                row_bytes = image[0].nbytes if len(image) else 0
                for start, count in zip(starts.tolist(), counts.tolist()):
                    if count:
                        _pwrite_all(fd, memoryview(image[start:start + count]).cast("B"), block + start * row_bytes)
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
