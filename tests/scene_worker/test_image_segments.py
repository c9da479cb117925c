"""The worker's side of image segments: it opens only the learner's sealed memfd holding the
request's nonce (through /proc/<pid>/fd/<fd>), never blocks on or writes into anything else there,
and writes each entry's rows where the request says."""

from __future__ import annotations

import dataclasses
import fcntl
import os
import secrets

import numpy as np
import pytest

from visfly_dist.aggregator.image_shm import ImageSegments
from visfly_dist.errors import ProtocolError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.image_segment import NONCE_BYTES, SEQ
from visfly_dist.scene_worker.image_segments import SegmentMappings

CAMS = (CameraSpec(name="depth", kind="depth", width=8, height=6),
        CameraSpec(name="rgb", kind="rgb", width=4, height=3))


@pytest.fixture
def learner():
    segments = ImageSegments("wseg", CAMS)
    yield segments
    segments.close()


@pytest.fixture
def worker():
    mappings = SegmentMappings()
    yield mappings
    mappings.close()


def _images(rows: int, value: int) -> dict[str, np.ndarray]:
    return {c.name: np.full((rows, *c.shape), value, c.dtype) for c in CAMS}


def test_entries_land_at_their_rows_and_the_header_says_when(learner, worker):
    step = learner.offer([("w", 1)], 5, 2)
    target = learner.target(step, ("w", 1), [3, 0], [0])  # entry 0: 2 rows at 3; entry 1: 3 rows at 0; spawn
    starts, counts = target.starts(np.array([2, 3, 2])), np.array([2, 3, 2])
    buffers, why = worker.views(target, CAMS, int((starts + counts).max()))
    assert why == "" and step.segment.seq(target.seq_offset) == 0  # being written
    rendered = np.concatenate([np.full(2, 1), np.full(3, 2), np.full(2, 3)])
    for cam in CAMS:
        order = np.concatenate([np.arange(s, s + c) for s, c in zip(starts, counts)])
        buffers[cam.name][order] = rendered.reshape(-1, *[1] * len(cam.shape)).astype(cam.dtype)
    assert worker.publish(target, buffers, starts, counts) == ""
    assert step.segment.seq(target.seq_offset) == target.seq
    for cam in CAMS:
        assert step.obs[cam.name][:, 0, 0, 0].tolist() == [2, 2, 2, 1, 1]
        assert step.spawn[cam.name][:, 0, 0, 0].tolist() == [3, 3]
    assert worker.names() == {target.name: target.size}
    learner.release(step)


def _sealed(size: int, seals: int) -> tuple[int, bytes]:
    fd = os.memfd_create("visfly-img-test", os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING)
    os.ftruncate(fd, size)
    nonce = secrets.token_bytes(NONCE_BYTES)
    os.pwrite(fd, nonce, 0)
    if seals:
        fcntl.fcntl(fd, fcntl.F_ADD_SEALS, seals)
    return fd, nonce


def test_only_a_sealed_memfd_with_the_nonce_is_used_and_nothing_else_is_written(learner, worker, tmp_path):
    step = learner.offer([("w", 1)], 2, 0)
    target = learner.target(step, ("w", 1), [0], [])
    unsealed, unsealed_nonce = _sealed(target.size, 0)
    shrinkable, shrinkable_nonce = _sealed(target.size, fcntl.F_SEAL_GROW | fcntl.F_SEAL_SEAL)
    regular = os.open(tmp_path / "file", os.O_RDWR | os.O_CREAT)
    os.ftruncate(regular, target.size)
    read_end, write_end = os.pipe()  # opening a pipe's end could block a reader: never here
    cases = {unsealed: unsealed_nonce, shrinkable: shrinkable_nonce, regular: target.nonce,
             read_end: target.nonce, write_end: target.nonce}
    try:
        for fd, nonce in cases.items():
            before = os.pread(fd, target.size, 0) if fd not in (read_end, write_end) else b""
            other = dataclasses.replace(target, fd=fd, nonce=nonce, name=f"{target.name}-{fd}")
            views, why = worker.views(other, CAMS, 2)
            assert views is None and "is not image segment" in why, why
            if before:
                assert os.pread(fd, target.size, 0) == before
        views, why = worker.views(dataclasses.replace(target, nonce=b"n" * NONCE_BYTES), CAMS, 2)
        assert views is None and "is not image segment" in why
        assert SEQ.unpack_from(step.segment.mm, target.seq_offset)[0] == 0  # nothing written into it either
        with pytest.raises(ProtocolError, match="request says"):
            worker.views(dataclasses.replace(target, size=target.size + 64), CAMS, 2)
        assert worker.names() == {}
        assert worker.views(target, CAMS, 2)[1] == ""
    finally:
        for fd in cases:
            os.close(fd)
    learner.release(step)


def test_a_segment_stays_usable_after_the_learner_retires_it(learner, worker):
    step = learner.offer([("w", 1)], 2, 0)
    target = learner.target(step, ("w", 1), [0], [])
    assert worker.views(target, CAMS, 2)[1] == ""
    learner.release(step, failed=True)  # retired: the learner's descriptor is closed
    assert step.segment.fd == -1
    late = dataclasses.replace(target, seq=target.seq + 1)  # a late request: the worker's own descriptor
    buffers, why = worker.views(late, CAMS, 2)
    assert why == "" and worker.publish(late, _images(2, 9), np.array([0]), np.array([2])) == ""
    assert step.obs["depth"].min() == 9  # the learner's mapping lives on with its views
    fresh = SegmentMappings()  # a worker that never opened it finds nothing of it
    try:
        views, why = fresh.views(late, CAMS, 2)
        assert views is None and ("cannot open" in why or "is not image segment" in why)
    finally:
        fresh.close()

