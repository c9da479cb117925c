"""The learner's image segments: ``/dev/shm`` files that workers on this host write a step's images into.

A step takes one segment for all its requests: each camera's block holds the observation's rows in
observation order (rows ``[0, k)``) and then the spawn rows. Each worker writes its agents' rows
where the request says (``entry_rows``) and its own sequence number in its own header slot
(``seq_offset``). The observation the learner hands out is a view of the segment: no copy between
the renderer's output and the torch observation. A segment is offered again only when nothing
refers to its images any more (every array handed out is a view of one ``uint8`` array of the
mapping, whose reference count says whether anyone still holds one), so an observation a caller
keeps is never written over; a caller that keeps many makes new segments, as fresh arrays would.

Invariants:
- A file exists only from its creation until the end of the first step that used it: then it is
  unlinked, and every side keeps its mapping. Nothing is left in ``/dev/shm`` even if any process
  is SIGKILLed later. Only a learner killed while a step is unanswered leaves files behind: a new
  :class:`ImageSegments` removes every ``visfly-img-*`` file of this user that no live process
  holds open or maps (:func:`remove_orphaned_segments`), so another live learner's files stay.
  An unlinked segment is offered only to steps whose workers all mapped it before.
- A segment is busy from the step that names it until the step was collected (:meth:`release`).
  A step with a failed request retires its segment: the worker may still write into it late, so
  the caller copies the step's images out and nobody is offered the segment again.
- Each request has its own sequence number; images count as written only if the worker's header
  slot holds that number when the reply is read and when the step is released (the worker writes
  0 while it writes), so a late write can never pass for a later request's images.
- A worker that cannot open a fresh segment, or finds another nonce, replies inline and is not
  offered a segment again (for that generation): it is on another host or sees another /dev/shm.
  Its rows are copied into the segment, so the observation is still one array.
"""

from __future__ import annotations

import logging
import mmap
import os
import secrets
import stat
import sys
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.image_segment import (
    NAME_PREFIX,
    NONCE_BYTES,
    SEQ,
    SEQ_OFFSET,
    SHM_DIR,
    SegmentTarget,
    align,
    block_bytes,
)
from visfly_dist.protocol.shm import files_in_use

log = logging.getLogger(__name__)

MAX_SEGMENTS = 6
"""Segments kept per run: the steps in flight, and the observations callers still hold."""
STEP_HEADER_BYTES = 4096
"""Header of a step segment: the nonce, then one sequence number per worker of the step (up to 510)."""
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


def _room(rows: int) -> int:
    """Rows a new segment makes room for: the next power of two (spawn rows vary step to step)."""
    return 1 << max(rows - 1, 0).bit_length()


@dataclass(eq=False)
class Segment:
    """One ``/dev/shm`` file, mapped here: per camera a block of ``obs_rows`` then ``spawn_rows`` images."""

    path: str
    nonce: bytes
    mm: mmap.mmap
    obs_rows: int
    spawn_rows: int
    blocks: dict[str, int]
    whole: np.ndarray  # uint8 view of the mapping; every array handed out is a view of it
    baseline: int = 0  # reference count of ``whole`` when nothing outside refers to it
    users: set[tuple[str, int]] = field(default_factory=set)  # (worker, generation) that mapped it
    linked: bool = True
    busy: bool = False
    retired: bool = False

    @property
    def name(self) -> str:
        return os.path.basename(self.path)

    def held(self) -> bool:
        """Whether an array handed out (an observation, a torch tensor over it) is still alive."""
        return sys.getrefcount(self.whole) > self.baseline

    def images(self, cameras: Sequence[CameraSpec], first: int, rows: int) -> dict[str, np.ndarray]:
        """Writable ``(rows, C, H, W)`` views of each camera's block from row ``first``."""
        out = {}
        for cam in cameras:
            row_bytes = block_bytes(cam, 1)
            start = self.blocks[cam.name] + first * row_bytes
            out[cam.name] = self.whole[start:start + rows * row_bytes].view(cam.dtype).reshape(rows, *cam.shape)
        return out

    def seq(self, offset: int) -> int:
        return SEQ.unpack_from(self.mm, offset)[0]

    def unlink(self) -> None:
        if self.linked:
            self.linked = False
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass

    def close(self) -> None:
        """Unlink, and unmap unless a view is still alive (the mapping then goes with the last view)."""
        self.unlink()
        self.whole = np.zeros(0, np.uint8)
        try:
            self.mm.close()
        except BufferError:
            pass


@dataclass(eq=False)
class StepImages:
    """The segment of one step: the observation's and the spawn rows' images (views), and the
    target of each worker asked to write there."""

    segment: Segment
    obs: dict[str, np.ndarray]
    spawn: dict[str, np.ndarray]
    fresh: bool  # the file was still linked when the step was sent (a worker that cannot open it is elsewhere)
    targets: dict[str, tuple[int, SegmentTarget]] = field(default_factory=dict)  # worker -> (generation, target)
    refused: bool = False  # a worker could not use it: it is not offered again
    written: set[str] = field(default_factory=set)  # workers whose images of this step were taken in place


class ImageSegments:
    """Every image segment of one learner (one run). Creating one removes orphaned segment files.

    Args:
        run_id: the run (part of every file name).
        cameras: the cameras whose images the segments hold.
    """

    def __init__(self, run_id: str, cameras: Sequence[CameraSpec]) -> None:
        self.run_id = run_id
        self.cameras = tuple(cameras)
        self._segments: list[Segment] = []
        self._refused: set[tuple[str, int]] = set()
        self._seq = 0
        remove_orphaned_segments()

    def offer(self, workers: Sequence[tuple[str, int]], obs_rows: int, spawn_rows: int) -> StepImages | None:
        """A segment for a step of ``obs_rows`` observation rows and ``spawn_rows`` spawn rows sent to
        ``workers`` (``(worker, generation)`` pairs), or None (every image travels inline)."""
        asked = {w for w in workers if w not in self._refused}
        if not asked or obs_rows + spawn_rows == 0:
            return None
        seg = next((s for s in self._segments if self._fits(s, asked, obs_rows, spawn_rows)), None)
        if seg is None:
            for old in [s for s in self._segments if not s.busy and not s.held()]:
                self._retire(old)  # too small, or unlinked before these workers mapped it
            while len(self._segments) >= MAX_SEGMENTS:
                self._retire(next(s for s in self._segments if not s.busy) if any(not s.busy for s in self._segments)
                             else self._segments[0])
            try:
                seg = self._create(_room(obs_rows), _room(spawn_rows))
            except OSError as exc:  # no /dev/shm, or no room in it: images travel inline
                log.warning("cannot create an image segment in %s (%s); images travel inline", SHM_DIR, exc)
                self._refused |= asked
                return None
            self._segments.append(seg)
        seg.busy = True
        return StepImages(seg, seg.images(self.cameras, 0, obs_rows), seg.images(self.cameras, seg.obs_rows, spawn_rows),
                          fresh=seg.linked)

    def target(self, step: StepImages, worker: tuple[str, int], obs_starts: Sequence[int],
               spawn_starts: Sequence[int]) -> SegmentTarget | None:
        """The ``image_segment`` of ``worker``'s request in ``step``: its entries' first rows (observation
        entries, then spawn entries), its own header slot; None if it gets its images inline."""
        lane = len(step.targets)
        seq_offset = SEQ_OFFSET + SEQ.size * lane
        if worker in self._refused or seq_offset + SEQ.size > STEP_HEADER_BYTES:
            return None
        seg = step.segment
        self._seq += 1
        rows = tuple(int(r) for r in obs_starts) + tuple(seg.obs_rows + int(r) for r in spawn_starts)
        target = SegmentTarget(seg.name, seg.nonce, len(seg.mm), self._seq, seg.blocks, seq_offset, rows)
        SEQ.pack_into(seg.mm, seq_offset, 0)
        step.targets[worker[0]] = (worker[1], target)
        return target

    def check(self, step: StepImages, worker_id: str, message: dict[str, Any]) -> tuple[bool, str]:
        """Whether ``worker_id``'s reply left its images in ``step``'s segment, and a problem (``""``
        if none) that fails the reply."""
        if worker_id not in step.targets:
            return False, ""
        generation, target = step.targets[worker_id]
        seg = step.segment
        if message.get("images_in_segment") is True:
            if seg.seq(target.seq_offset) != target.seq:
                return False, f"image segment {seg.name} does not hold the images of request {target.seq}"
            seg.users.add((worker_id, generation))
            step.written.add(worker_id)
            return True, ""
        if "segment_refused" in message:
            step.refused = True
            if step.fresh:
                log.info("worker %s replies inline from now on: %s", worker_id, message["segment_refused"])
                self._refused.add((worker_id, generation))
        return False, ""

    def release(self, step: StepImages, failed: bool = False) -> list[str]:
        """Done with ``step`` (every reply read). ``failed``: a request got no usable reply (the
        segment is retired; the caller copies the images out).

        Returns:
            Workers whose images of this step were taken in place and written over since their
            reply was read (a late write): their rows are not to be trusted. A worker whose reply
            did not come is not one of them (it failed already).
        """
        seg = step.segment
        seg.unlink()
        seg.busy = False
        over = [w for w in step.written if seg.seq(step.targets[w][1].seq_offset) != step.targets[w][1].seq]
        if failed or over or step.refused or seg.retired:
            self._retire(seg)
        return over

    def _fits(self, seg: Segment, workers: set[tuple[str, int]], obs_rows: int, spawn_rows: int) -> bool:
        return (not seg.busy and not seg.retired and seg.obs_rows >= obs_rows and seg.spawn_rows >= spawn_rows
                and (seg.linked or workers <= seg.users) and not seg.held())

    def _create(self, obs_rows: int, spawn_rows: int) -> Segment:
        blocks, size = {}, STEP_HEADER_BYTES
        for cam in self.cameras:
            blocks[cam.name] = size
            size = align(size + block_bytes(cam, obs_rows + spawn_rows))
        nonce = secrets.token_bytes(NONCE_BYTES)
        name = f"{NAME_PREFIX}{_name_part(self.run_id)}-{nonce[:8].hex()}"
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
        seg = Segment(path, nonce, mm, obs_rows, spawn_rows, blocks, np.frombuffer(mm, np.uint8))
        seg.baseline = sys.getrefcount(seg.whole)
        return seg

    def _retire(self, seg: Segment) -> None:
        """Unlink a segment and never offer it again; unmapped once no step and no caller holds it."""
        seg.retired = True
        seg.unlink()
        if seg in self._segments:
            self._segments.remove(seg)
        if not seg.busy:
            seg.close()

    def files(self) -> list[str]:
        """Paths of the segment files still on disk (tests, diagnostics)."""
        return [s.path for s in self._segments if s.linked]

    def close(self) -> None:
        """Unlink and unmap every segment (idempotent)."""
        for seg in self._segments:
            seg.close()
        self._segments.clear()
