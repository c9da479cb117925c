"""The learner's image segments: sealed memfds that workers on this host write a step's images into.

A step takes one segment for all its requests: each camera's block holds the observation's rows in
observation order (rows ``[0, k)``) and then the spawn rows. Each worker writes its agents' rows
where the request says (``entry_rows``) and its own sequence number in its own header slot
(``seq_offset``). The observation the learner hands out is a view of the segment: no copy between
the renderer's output and the torch observation.

Ownership (leases): each time a segment is offered to a step, its images are views of a fresh
``uint8`` array over the mapping, the step's *lease*, of which the segment keeps only a
``weakref``. Every array made from those views (a slice, a reshape, a ``torch.from_numpy``
tensor, a view of that tensor, ``tensor.numpy()``) refers to the lease through ``.base`` or its
storage, so the lease lives exactly as long as anything can reach the images. A segment is
offered again only when it is not busy (its step was released) and its last lease is gone. An
observation a caller keeps is therefore never written over, under any number of references; a
caller that keeps many makes new segments, as fresh arrays would. The rule needs no reference
counts: a lease kept alive longer (a reference cycle, another interpreter's collector) only delays
the reuse.

Invariants:
- A segment is a memfd sealed against shrinking and growing (and against further seals) before it
  is mapped: no process can truncate it, so reading it never raises SIGBUS. It is no file in any
  directory: it lives while the learner holds its descriptor, a mapping of it, or a worker its own
  descriptor, and goes with the last of them (a killed learner leaves nothing behind).
- Workers open it through ``/proc/<learner pid>/fd/<fd>`` for as long as the learner keeps it;
  the learner closes the descriptor when it retires the segment.
- A segment is busy from the step that names it until the step was collected (:meth:`release`).
  A step with a failed request retires its segment: the worker may still write into it late, so
  the caller copies the step's images out and nobody is offered the segment again.
- Each request has its own sequence number; images count as written only if the worker's header
  slot holds that number when the reply is read and when the step is released (the worker writes
  0 while it writes), so a late write can never pass for a later request's images.
- A worker that cannot open the segment, or finds another nonce, replies inline and is not offered
  a segment again (for that generation): it is on another host or in another pid namespace. Its
  rows are copied into the segment, so the observation is still one array.
"""

from __future__ import annotations

import fcntl
import logging
import mmap
import os
import secrets
import weakref
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Sequence

import numpy as np

from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.image_segment import (
    NAME_PREFIX,
    NONCE_BYTES,
    SEALS,
    SEQ,
    SEQ_OFFSET,
    SegmentTarget,
    align,
    block_bytes,
)

log = logging.getLogger(__name__)

MAX_SEGMENTS = 6
"""Segments kept per run: the steps in flight, and the observations callers still hold (more when a
caller says it keeps more: :meth:`ImageSegments.hold`)."""
STEP_HEADER_BYTES = 4096
"""Header of a step segment: the nonce, then one sequence number per worker of the step (up to 510)."""
NAME_PART_CHARS = 48


def _name_part(value: str) -> str:
    return "".join(c if c.isalnum() or c in "_-" else "_" for c in value)[:NAME_PART_CHARS]


def _room(rows: int) -> int:
    """Rows a new segment makes room for: the next power of two (spawn rows vary step to step)."""
    return 1 << max(rows - 1, 0).bit_length()


class RowLayout(NamedTuple):
    """One camera's image rows in a segment's block: its name, bytes per row, dtype and image shape."""

    name: str
    row_bytes: int
    dtype: np.dtype
    shape: tuple[int, int, int]


@dataclass(eq=False)
class Segment:
    """One sealed memfd, mapped here: per camera a block of ``obs_rows`` then ``spawn_rows`` images."""

    name: str
    fd: int  # the learner's descriptor, which workers open through /proc; -1 once closed
    nonce: bytes
    mm: mmap.mmap
    obs_rows: int
    spawn_rows: int
    blocks: dict[str, int]
    lease: weakref.ref[np.ndarray] | None = None  # the array the last step's images are views of
    busy: bool = False
    retired: bool = False

    def held(self) -> bool:
        """Whether anything made from the last lease (an observation, a torch tensor over it) is alive."""
        return self.lease is not None and self.lease() is not None

    def lend(self, cameras: Sequence[RowLayout], obs_rows: int,
             spawn_rows: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Writable ``(rows, C, H, W)`` views of each camera's observation and spawn rows, all of a new lease."""
        lease = np.frombuffer(self.mm, np.uint8)  # its base is no ndarray: views of it keep it as theirs
        self.lease = weakref.ref(lease)

        def views(first: int, rows: int) -> dict[str, np.ndarray]:
            out = {}
            for name, row_bytes, dtype, shape in cameras:
                start = self.blocks[name] + first * row_bytes
                out[name] = lease[start:start + rows * row_bytes].view(dtype).reshape(rows, *shape)
            return out

        return views(0, obs_rows), views(self.obs_rows, spawn_rows)

    def seq(self, offset: int) -> int:
        return SEQ.unpack_from(self.mm, offset)[0]

    def close(self) -> None:
        """Close the descriptor (no worker can open the segment any more) and unmap unless a lease is
        still alive (the mapping then goes with it)."""
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1
        try:
            self.mm.close()
        except BufferError:
            pass


@dataclass(eq=False)
class StepImages:
    """The segment of one step: the observation's and the spawn rows' images (views of its lease),
    and the target of each worker asked to write there."""

    segment: Segment
    obs: dict[str, np.ndarray]
    spawn: dict[str, np.ndarray]
    targets: dict[str, tuple[int, SegmentTarget]] = field(default_factory=dict)  # worker -> (generation, target)
    refused: bool = False  # a worker could not use it: it is not offered again
    written: set[str] = field(default_factory=set)  # workers whose images of this step were taken in place


class ImageSegments:
    """Every image segment of one learner (one run).

    Args:
        run_id: the run (part of every segment's name).
        cameras: the cameras whose images the segments hold.
    """

    def __init__(self, run_id: str, cameras: Sequence[CameraSpec]) -> None:
        self.run_id = run_id
        self.cameras = tuple(cameras)
        self._layouts = [RowLayout(c.name, block_bytes(c, 1), c.dtype, c.shape) for c in self.cameras]  # once, not per step
        self.pid = os.getpid()  # whose /proc/<pid>/fd the workers open the segments through
        self._segments: list[Segment] = []
        self._refused: set[tuple[str, int]] = set()
        self._seq = 0
        self.max_segments = MAX_SEGMENTS
        self._spawn_room = 0  # the most spawn rows a segment was made for

    def hold(self, observations: int) -> None:
        """A caller keeps up to ``observations`` observations at once (a trainer's rollout): keep that
        many segments more, so that one it lets go is offered again instead of a new one made."""
        self.max_segments = MAX_SEGMENTS + max(0, int(observations))

    def offer(self, workers: Sequence[tuple[str, int]], obs_rows: int, spawn_rows: int) -> StepImages | None:
        """A segment for a step of ``obs_rows`` observation rows and ``spawn_rows`` spawn rows sent to
        ``workers`` (``(worker, generation)`` pairs), or None (every image travels inline)."""
        asked = {w for w in workers if w not in self._refused}
        if not asked or obs_rows + spawn_rows == 0:
            return None
        seg = next((s for s in self._segments if self._fits(s, obs_rows, spawn_rows)), None)
        if seg is None:
            for old in [s for s in self._segments if not s.busy and not s.held()]:
                self._retire(old)  # too small
            while len(self._segments) >= self.max_segments:
                self._retire(next(s for s in self._segments if not s.busy) if any(not s.busy for s in self._segments)
                             else self._segments[0])
            try:
                # as many spawn rows as any step asked for: a caller that holds many observations
                # cycles through many segments, and one made smaller would soon be made again
                self._spawn_room = max(self._spawn_room, _room(spawn_rows))
                seg = self._create(_room(obs_rows), self._spawn_room)
            except OSError as exc:  # out of memory or descriptors: images travel inline
                log.warning("cannot create an image segment (%s); images travel inline", exc)
                self._refused |= asked
                return None
            self._segments.append(seg)
        seg.busy = True
        return StepImages(seg, *seg.lend(self._layouts, obs_rows, spawn_rows))

    def target(self, step: StepImages, worker: tuple[str, int], obs_starts: Sequence[int] | np.ndarray,
               spawn_starts: Sequence[int] | np.ndarray) -> SegmentTarget | None:
        """The ``image_segment`` of ``worker``'s request in ``step``: its entries' first rows (observation
        entries, then spawn entries, as step plans hold them), its own header slot; None if it gets its
        images inline."""
        lane = len(step.targets)
        seq_offset = SEQ_OFFSET + SEQ.size * lane
        if worker in self._refused or seq_offset + SEQ.size > STEP_HEADER_BYTES:
            return None
        seg = step.segment
        self._seq += 1
        rows = np.asarray(obs_starts, np.int64)  # the plan's array as it is when no spawn entry follows
        if len(spawn_starts):
            rows = np.concatenate((rows, np.asarray(spawn_starts, np.int64) + seg.obs_rows))
        target = SegmentTarget(seg.name, seg.nonce, len(seg.mm), self._seq, seg.blocks, self.pid, seg.fd,
                               seq_offset, rows)
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
            step.written.add(worker_id)
            return True, ""
        if "segment_refused" in message:
            step.refused = True
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
        seg.busy = False
        over = [w for w in step.written if seg.seq(step.targets[w][1].seq_offset) != step.targets[w][1].seq]
        if failed or over or step.refused or seg.retired:
            self._retire(seg)
        return over

    def live(self) -> list[str]:
        """Names of the segments this learner keeps (diagnostics, tests)."""
        return [s.name for s in self._segments]

    def _fits(self, seg: Segment, obs_rows: int, spawn_rows: int) -> bool:
        return (not seg.busy and not seg.retired and seg.obs_rows >= obs_rows and seg.spawn_rows >= spawn_rows
                and not seg.held())

    def _create(self, obs_rows: int, spawn_rows: int) -> Segment:
        blocks, size = {}, STEP_HEADER_BYTES
        for cam in self.cameras:
            blocks[cam.name] = size
            size = align(size + block_bytes(cam, obs_rows + spawn_rows))
        nonce = secrets.token_bytes(NONCE_BYTES)
        name = f"{NAME_PREFIX}{_name_part(self.run_id)}-{nonce[:8].hex()}"
        fd = os.memfd_create(name, os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING)
        try:
            os.posix_fallocate(fd, 0, size)  # the pages exist now: no memory fails here, not as SIGBUS later
            fcntl.fcntl(fd, fcntl.F_ADD_SEALS, SEALS)
            mm = mmap.mmap(fd, size)
        except BaseException:
            os.close(fd)
            raise
        mm[:NONCE_BYTES] = nonce
        return Segment(name, fd, nonce, mm, obs_rows, spawn_rows, blocks)

    def _retire(self, seg: Segment) -> None:
        """Never offer a segment again; closed once no step holds it (unmapped once no lease does)."""
        seg.retired = True
        if seg in self._segments:
            self._segments.remove(seg)
        if not seg.busy:
            seg.close()

    def close(self) -> None:
        """Close and unmap every segment (idempotent)."""
        for seg in self._segments:
            seg.close()
        self._segments.clear()
