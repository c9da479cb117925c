"""The learner's image segments: ``/dev/shm`` files that workers on this host write their images into.

Per worker (and worker generation) the learner holds a few segments (:data:`MAX_PER_WORKER`), one
per request in flight: a request takes a free segment big enough for its rows, or a new one with
room for the next power of two of rows (a segment that is too small is retired, never resized: a
new file gets a new name). The step request
names it (:class:`~visfly_dist.protocol.image_segment.SegmentTarget`); the worker proves it is on
this host by finding the nonce there, writes the images, then the request's sequence number.

Invariants:
- A file exists only from its creation until the worker's first answer to a request naming it:
  then it is unlinked, and both sides keep their mappings. Nothing is left in ``/dev/shm`` even if
  either process is SIGKILLed later. Retired segments, dropped workers and :meth:`close` unlink
  too. Only a learner killed while a request is unanswered leaves files behind: a new
  :class:`ImageSegments` removes every ``visfly-img-*`` file of this user that no live process
  holds open or maps (:func:`remove_orphaned_segments`), so another live learner's files stay.
- A segment is busy from the request that names it until the reply was read (:meth:`release`). A
  request that failed (no reply, timeout) retires its segment: the worker may still write into
  it late, so it is never handed to another request.
- Each request has its own sequence number; the images are read only if the header holds that
  number before and after the copy (the worker writes 0 while it writes images), so a late write
  can never pass for a later request's images.
- A worker that cannot open a fresh segment, or finds another nonce, replies inline and is not
  offered a segment again (for that generation): it is on another host or sees another /dev/shm.
"""

from __future__ import annotations

import logging
import mmap
import os
import secrets
import stat
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.image_segment import (
    NAME_PREFIX, NONCE_BYTES, SEQ, SEQ_OFFSET, SHM_DIR, SegmentTarget, block_view, layout,
)
from visfly_dist.protocol.shm import files_in_use

log = logging.getLogger(__name__)

MAX_PER_WORKER = 4
NAME_PART_CHARS = 48


def remove_orphaned_segments() -> list[str]:
    """Unlink the image segment files in :data:`SHM_DIR` that are this user's and nobody's any more.

    A file is an orphan when no live process holds it open or maps it (``/proc/*/fd`` and
    ``/proc/*/maps``): its learner was killed before the worker answered. A live learner maps
    each of its files from creation to unlink, so its files are never removed.

    Returns:
        The removed paths.
    """
    try:
        names = [n for n in os.listdir(SHM_DIR) if n.startswith(NAME_PREFIX)]
    except OSError:  # no /dev/shm: images travel inline anyway
        return []
    mine = []
    for name in names:
        path = os.path.join(SHM_DIR, name)
        try:
            st = os.lstat(path)
        except FileNotFoundError:
            continue
        if st.st_uid == os.getuid() and stat.S_ISREG(st.st_mode):
            mine.append(path)
    removed = []
    for path in sorted(set(mine) - files_in_use(mine)):
        try:
            os.unlink(path)
        except FileNotFoundError:
            continue
        removed.append(path)
    if removed:
        log.info("removed %d image segment file(s) left in %s by a learner that was killed", len(removed), SHM_DIR)
    return removed


def _name_part(value: str) -> str:
    return "".join(c if c.isalnum() or c in "_-" else "_" for c in value)[:NAME_PART_CHARS]


@dataclass(eq=False)
class Segment:
    """One ``/dev/shm`` file of one worker, mapped here."""

    worker_id: str
    generation: int
    path: str
    nonce: bytes
    mm: mmap.mmap
    linked: bool = True
    busy: bool = False
    confirmed: bool = False  # the worker wrote images into it at least once
    retired: bool = False

    @property
    def name(self) -> str:
        return os.path.basename(self.path)

    def unlink(self) -> None:
        if self.linked:
            self.linked = False
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass

    def close(self) -> None:
        self.unlink()
        try:
            self.mm.close()
        except BufferError:  # a view is still alive (a caller's observation never is: it is a copy)
            pass


@dataclass(eq=False)
class Lease:
    """A segment taken by one request: its target and its rows."""

    segment: Segment
    target: SegmentTarget
    rows: int
    read: bool = field(default=False)


class ImageSegments:
    """Every image segment of one learner (one run). Creating one removes orphaned segment files.

    Args:
        run_id: the run (part of every file name).
        cameras: the cameras whose images the segments hold.
    """

    def __init__(self, run_id: str, cameras: Sequence[CameraSpec]) -> None:
        self.run_id = run_id
        self.cameras = tuple(cameras)
        self._segments: dict[str, list[Segment]] = {}
        self._refused: set[tuple[str, int]] = set()
        self._seq = 0
        remove_orphaned_segments()

    def offer(self, worker_id: str, generation: int, rows: int) -> Lease | None:
        """A segment for a request of ``rows`` image rows to this worker, or None (send images inline)."""
        if rows == 0 or (worker_id, generation) in self._refused:
            return None
        mine = self._segments.setdefault(worker_id, [])
        for seg in [s for s in mine if s.generation != generation]:
            self._retire(seg)
        blocks, need = layout(self.cameras, rows)
        free = [s for s in mine if not s.busy and not s.retired]
        seg = next((s for s in free if len(s.mm) >= need), None)
        if seg is None:
            for small in free:
                self._retire(small)
            if len([s for s in mine if not s.retired]) >= MAX_PER_WORKER:
                return None
            try:  # room for the next power of two of rows: spawn rows vary step to step
                seg = self._create(worker_id, generation, layout(self.cameras, 1 << (rows - 1).bit_length())[1])
            except OSError as exc:  # no /dev/shm, or no room in it: images travel inline
                log.warning("cannot create an image segment of %d bytes in %s (%s); images travel inline",
                            need, SHM_DIR, exc)
                self._refused.add((worker_id, generation))
                return None
            mine.append(seg)
        seg.busy = True
        self._seq += 1
        return Lease(seg, SegmentTarget(seg.name, seg.nonce, len(seg.mm), self._seq, blocks), rows)

    def _create(self, worker_id: str, generation: int, size: int) -> Segment:
        nonce = secrets.token_bytes(NONCE_BYTES)
        name = f"{NAME_PREFIX}{_name_part(self.run_id)}-{_name_part(worker_id)}-{nonce[:8].hex()}"
        path = os.path.join(SHM_DIR, name)
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
        try:
            os.posix_fallocate(fd, 0, size)  # the pages exist now: a full /dev/shm fails here, not as SIGBUS later
            mm = mmap.mmap(fd, size)
        except BaseException:
            os.unlink(path)
            raise
        finally:
            os.close(fd)
        mm[:NONCE_BYTES] = nonce
        return Segment(worker_id, generation, path, nonce, mm)

    def images(self, lease: Lease, message: dict[str, Any]) -> tuple[dict[str, np.ndarray] | None, str]:
        """The answered request's images: read-only views of the segment when the worker wrote them
        there, None when it replied inline; and a problem (``""`` if none) that fails the reply.

        Unlinks the segment's file (the worker has answered). A refused fresh segment stops offers
        to that worker; a refused segment it used before (it restarted) is retired.
        """
        seg = lease.segment
        seg.unlink()
        if message.get("images_in_segment") is True:
            if SEQ.unpack_from(seg.mm, SEQ_OFFSET)[0] != lease.target.seq:
                return None, f"image segment {seg.name} does not hold the images of request {lease.target.seq}"
            seg.confirmed = lease.read = True
            views = {c.name: block_view(seg.mm, lease.target.blocks[c.name], c, lease.rows) for c in self.cameras}
            for view in views.values():
                view.flags.writeable = False
            return views, ""
        if "segment_refused" in message:
            if seg.confirmed:
                self._retire(seg)
            else:
                log.info("worker %s replies inline from now on: %s", seg.worker_id, message["segment_refused"])
                self._refused.add((seg.worker_id, seg.generation))
                self.drop_worker(seg.worker_id)
        return None, ""

    def release(self, lease: Lease, failed: bool = False) -> bool:
        """Done with ``lease``'s request. ``failed``: it got no usable reply (the segment is retired).

        Returns:
            False if images were read and the segment no longer holds this request's (written over
            during the copy): the copied rows are not to be trusted.
        """
        seg = lease.segment
        intact = not lease.read or SEQ.unpack_from(seg.mm, SEQ_OFFSET)[0] == lease.target.seq
        seg.busy = False
        if failed or not intact or seg.retired:
            self._retire(seg)
        return intact

    def _retire(self, seg: Segment) -> None:
        """Unlink a segment and never offer it again; unmapped once no request holds it."""
        seg.retired = True
        seg.unlink()
        if not seg.busy:
            seg.close()
            mine = self._segments.get(seg.worker_id, [])
            if seg in mine:
                mine.remove(seg)

    def drop_worker(self, worker_id: str) -> None:
        """Retire every segment of a worker that failed or left (a later generation gets fresh ones)."""
        for seg in list(self._segments.get(worker_id, [])):
            self._retire(seg)

    def keep_only(self, live: dict[str, int]) -> None:
        """Retire the segments of workers that are gone or restarted (``live``: worker -> generation)."""
        for worker_id, segs in list(self._segments.items()):
            for seg in list(segs):
                if live.get(worker_id) != seg.generation:
                    self._retire(seg)
            if not segs:
                del self._segments[worker_id]

    def files(self) -> list[str]:
        """Paths of the segment files still on disk (tests, diagnostics)."""
        return [s.path for segs in self._segments.values() for s in segs if s.linked]

    def close(self) -> None:
        """Unlink and unmap every segment (idempotent)."""
        for segs in self._segments.values():
            for seg in segs:
                seg.close()
        self._segments.clear()
