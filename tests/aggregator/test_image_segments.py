"""Images through a sealed memfd segment: equal to the inline path bit for bit, proven local by a
nonce, refused with typed errors when malformed, never read when they are another request's, never
written over while held, and no file in /dev/shm (real worker processes, real Zenoh)."""

from __future__ import annotations

import dataclasses
import gc
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.aggregator.conftest import make_aggregator, reference, spawn_poses
from tests.helpers import REPO, call, client_session, wait_for
from visfly_dist.aggregator import image_shm
from visfly_dist.aggregator.image_shm import ImageSegments
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.image_segment import HEADER_BYTES, SEQ, SegmentTarget
from visfly_dist.protocol.messages import Health, LoadScene, ScenePoses, StepRequest

pytestmark = pytest.mark.worker

RUN = f"seg{os.getpid()}"
CAMS = (CameraSpec(name="depth", kind="depth", width=32, height=24),
        CameraSpec(name="seg", kind="segmentation", width=16, height=12),
        CameraSpec(name="rgb", kind="rgb", width=16, height=12))


def _poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yaw = rng.uniform(-np.pi, np.pi, n)
    poses = np.zeros((n, 7), np.float32)
    poses[:, :3] = rng.uniform((2.0, -4.0, 1.0), (14.0, 4.0, 3.0), (n, 3))
    poses[:, 3], poses[:, 6] = np.cos(yaw / 2), np.sin(yaw / 2)
    return poses


def _shm_files(run: str) -> list[str]:
    """Files of the run in /dev/shm: a segment is never one."""
    return [p for p in os.listdir("/dev/shm") if p.startswith(f"visfly-img-{run}-")]


@pytest.fixture(scope="module")
def served(worker_factory):
    """A worker holding two scenes, a client session to it, and a learner's segment set."""
    proc = worker_factory(RUN)
    with client_session(proc.endpoint) as session:
        for key, source in (("a", "gen:garage-stones?seed=3"), ("b", "gen:pillars?seed=4")):
            ok, reply = call(session, proc.rpc_key, LoadScene(key, source, CAMS).to_message(), timeout=60.0)
            assert ok, reply
        segments = ImageSegments(RUN, CAMS)
        yield proc, session, segments
        segments.close()
    assert _shm_files(RUN) == []


def _offer(segments: ImageSegments, worker: str, rows: int, generation: int = 1):
    """A step segment for one request of ``rows`` poses (entries a: 3 rows, b: the rest) and its target."""
    step = segments.offer([(worker, generation)], rows, 0)
    if step is None:
        return None, None
    return step, segments.target(step, (worker, generation), [0, 3], [])


def _step(poses: np.ndarray, target: SegmentTarget | None = None) -> dict:
    request = StepRequest((ScenePoses("a", poses[:3]), ScenePoses("b", poses[3:])), image_segment=target)
    return request.to_message()


def test_segment_images_equal_inline_images_bit_for_bit(served):
    proc, session, segments = served
    poses = _poses(7)
    ok, inline = call(session, proc.rpc_key, _step(poses))
    assert ok and "images_in_segment" not in inline and "segment_refused" not in inline
    for _ in range(2):  # the second step uses the descriptor the worker opened for the first
        step, target = _offer(segments, proc.worker_id, len(poses))
        ok, reply = call(session, proc.rpc_key, _step(poses, target))
        assert ok and reply["images_in_segment"] is True and reply["images"] == {}
        assert segments.check(step, proc.worker_id, reply) == (True, "")
        for cam in CAMS:
            assert step.obs[cam.name].dtype == inline["images"][cam.name].dtype
            np.testing.assert_array_equal(step.obs[cam.name], inline["images"][cam.name])
        for key in ("collision", "inside", "nearest", "distance"):
            np.testing.assert_array_equal(reply[key], inline[key])
        assert segments.release(step) == [] and _shm_files(RUN) == []
        del step  # nothing holds its images any more: the next step may use the segment again
    ok, health = call(session, proc.rpc_key, Health().to_message())
    assert health["image_segments"] == {target.name: target.size}


def test_a_segment_is_not_offered_while_its_images_are_held_and_entries_land_at_their_rows(served):
    proc, session, segments = served
    poses = _poses(7, seed=5)
    ok, inline = call(session, proc.rpc_key, _step(poses))
    step = segments.offer([(proc.worker_id, 1)], 9, 0)
    target = segments.target(step, (proc.worker_id, 1), [5, 0], [])  # entry a at rows 5-7, b at rows 0-3
    ok, reply = call(session, proc.rpc_key, _step(poses, target))
    assert ok and segments.check(step, proc.worker_id, reply) == (True, "")
    depth = step.obs["depth"]
    np.testing.assert_array_equal(depth[5:8], inline["images"]["depth"][:3])
    np.testing.assert_array_equal(depth[0:4], inline["images"]["depth"][3:])
    assert segments.release(step) == []
    held = depth[0]  # a caller keeps one image: the segment stays theirs
    kept = held.copy()
    other, other_target = _offer(segments, proc.worker_id, 7)
    assert other.segment is not step.segment
    ok, reply = call(session, proc.rpc_key, _step(_poses(7, seed=6), other_target))
    assert ok and segments.check(other, proc.worker_id, reply) == (True, "")
    np.testing.assert_array_equal(held, kept)
    segments.release(other, failed=True)
    del held, depth, step
    again, _ = _offer(segments, proc.worker_id, 7)
    assert again.segment.name == target.name  # free again once nothing refers to its images
    segments.release(again)
    assert _shm_files(RUN) == []


def test_a_segment_the_worker_cannot_see_gets_the_images_inline(served):
    proc, session, segments = served
    poses = _poses(7, seed=1)
    ok, inline = call(session, proc.rpc_key, _step(poses))
    other = ImageSegments(RUN, CAMS)
    lease, lease_target = _offer(other, "other", len(poses))  # a real segment, another nonce sent
    for target, why in ((dataclasses.replace(lease_target, nonce=b"x" * 16), "is not image segment"),
                        (dataclasses.replace(lease_target, fd=lease_target.fd + 1000), "cannot open"),
                        # another process's descriptor: what a worker in another pid namespace finds
                        (dataclasses.replace(lease_target, pid=proc.pid, fd=0), "is not image segment")):
        ok, reply = call(session, proc.rpc_key, _step(poses, target))
        assert ok and why in reply["segment_refused"] and "images_in_segment" not in reply
        for cam in CAMS:
            np.testing.assert_array_equal(reply["images"][cam.name], inline["images"][cam.name])
    other.close()
    learner = ImageSegments(RUN, CAMS)  # the learner stops offering a segment to that worker
    refused, refused_target = _offer(learner, "w", len(poses))
    refused.segment.mm[:16] = b"y" * 16  # as if another host's process held this descriptor
    ok, reply = call(session, proc.rpc_key, _step(poses, refused_target))
    assert learner.check(refused, "w", reply) == (False, "") and learner.release(refused) == []
    assert learner.offer([("w", 1)], len(poses), 0) is None and learner.live() == []
    assert learner.offer([("w", 2)], len(poses), 0) is not None  # a restarted worker is asked again
    learner.close()


# Another process of the user, with the worker's access to the learner's descriptors.
RESIZER = r"""
import fcntl, os, sys
path = sys.argv[1]
attempts = {
    "truncate": lambda: os.truncate(path, 64),
    "open with O_TRUNC": lambda: os.close(os.open(path, os.O_RDWR | os.O_TRUNC)),
    "grow": lambda: os.truncate(path, 1 << 30),
    "fallocate past the end": lambda: os.posix_fallocate(os.open(path, os.O_RDWR), 0, 1 << 30),
    "add a write seal": lambda: fcntl.fcntl(os.open(path, os.O_RDWR), fcntl.F_ADD_SEALS, fcntl.F_SEAL_WRITE),
    "add a future-write seal": lambda: fcntl.fcntl(os.open(path, os.O_RDWR), fcntl.F_ADD_SEALS, 0x10),
}
for what, attempt in attempts.items():
    try:
        attempt()
        print(what, "succeeded")
    except PermissionError:
        pass
print(os.stat(path).st_size)
"""


def test_another_process_cannot_resize_a_segment_and_the_worker_keeps_writing_in_place(served):
    """A process of the user that opens the learner's segment (as a worker does) cannot truncate,
    grow or write-seal it (with a /dev/shm file, a truncate killed the reader with SIGBUS): the
    learner reads every byte, and the worker keeps writing in place."""
    proc, session, _ = served
    poses = _poses(7, seed=9)
    ok, inline = call(session, proc.rpc_key, _step(poses))
    learner = ImageSegments(RUN, CAMS)
    step, target = _offer(learner, proc.worker_id, len(poses))
    ok, reply = call(session, proc.rpc_key, _step(poses, target))
    assert ok and reply["images_in_segment"] is True  # the worker holds the segment open now
    assert learner.check(step, proc.worker_id, reply) == (True, "") and learner.release(step) == []
    resizer = subprocess.run([sys.executable, "-c", RESIZER, target.path()], capture_output=True, text=True,
                             timeout=60, cwd=REPO)
    assert resizer.returncode == 0 and resizer.stdout.split() == [str(target.size)], resizer.stdout + resizer.stderr
    assert len(step.segment.mm[:]) == target.size  # every page reads (a truncated file raised SIGBUS here)
    for cam in CAMS:
        np.testing.assert_array_equal(step.obs[cam.name], inline["images"][cam.name])
    del step
    again, again_target = _offer(learner, proc.worker_id, len(poses))
    assert again_target.name == target.name
    ok, reply = call(session, proc.rpc_key, _step(poses, again_target))
    assert ok and reply["images_in_segment"] is True and "segment_refused" not in reply
    assert learner.check(again, proc.worker_id, reply) == (True, "")
    for cam in CAMS:
        np.testing.assert_array_equal(again.obs[cam.name], inline["images"][cam.name])
    assert learner.release(again) == [] and proc.poll() is None
    del again
    learner.close()


@pytest.mark.parametrize("change, match", [
    (dict(name="../../tmp/visfly-img-x"), "no path separators"),
    (dict(name="visfly-img-a/b"), "no path separators"),
    (dict(name="visfly-img-a..b"), "no dots"),
    (dict(name="visfly-img-" + "a" * 300), "at most 200"),
    (dict(name="passwd"), "must be 'visfly-img-'"),
    (dict(nonce=b"short"), "nonce must be 16 bytes"),
    (dict(seq=0), "seq=0"),
    (dict(size=10), "size=10"),
    ("size+64", "request says"),
    (dict(pid=0), "pid=0"),
    (dict(pid=-5), "pid=-5"),
    (dict(fd=-1), "fd=-1"),
    (dict(fd="3"), "fd='3'"),
    (dict(blocks={"depth": HEADER_BYTES}), "this scene's cameras"),
    (dict(seq_offset=20), "seq_offset=20"),
    (dict(seq_offset=8), "seq_offset=8"),
    (dict(seq_offset=image_shm.STEP_HEADER_BYTES), "first block"),
    (dict(entry_rows=[0]), "entry_rows has 1 rows for 2 scene entries"),
    (dict(entry_rows=[0, -3]), "row indices >= 0"),
    (dict(entry_rows=[0, 1 << 20]), "ends past the segment"),
    ("overlap", "overlaps the header or another block"),
    ("past the end", "ends past the segment"),
])
def test_malformed_segment_requests_are_refused_and_the_worker_keeps_serving(served, change, match):
    proc, session, segments = served
    poses = _poses(7, seed=2)
    lease, target = _offer(segments, proc.worker_id, len(poses))
    if change == "size+64":
        target = dataclasses.replace(target, size=target.size + 64)
    elif change == "overlap":
        target = dataclasses.replace(target, blocks={**target.blocks, "seg": target.blocks["depth"] + 64})
    elif change == "past the end":
        target = dataclasses.replace(target, blocks={**target.blocks, "rgb": target.size - 64})
    else:
        message = _step(poses, target)
        message["image_segment"].update(change)
    ok, err = call(session, proc.rpc_key, message if isinstance(change, dict) else _step(poses, target))
    assert not ok and err["code"] == "bad_request" and match in err["message"], err
    segments.release(lease, failed=True)
    ok, health = call(session, proc.rpc_key, Health().to_message())
    assert ok and health["scenes"] == ["a", "b"]
    assert not Path("/tmp/visfly-img-x").exists()


def test_images_of_another_request_are_never_read(served):
    proc, session, segments = served
    poses = _poses(7, seed=3)
    first, first_target = _offer(segments, proc.worker_id, len(poses))
    ok, reply = call(session, proc.rpc_key, _step(poses, first_target))
    assert segments.check(first, proc.worker_id, reply)[1] == "" and segments.release(first) == []
    first_segment = first.segment
    del first
    later, later_target = _offer(segments, proc.worker_id, len(poses))
    assert later.segment is first_segment and later_target.seq > first_target.seq
    # The first request served again (as a late duplicate would be): its number lands in the header.
    ok, stale = call(session, proc.rpc_key, _step(poses, first_target))
    in_place, problem = segments.check(later, proc.worker_id, stale)
    assert not in_place and f"request {later_target.seq}" in problem
    segments.release(later, failed=True)
    # A failed request's segment is retired: the worker may still write into it, so nobody reads it again.
    fresh, fresh_target = _offer(segments, proc.worker_id, len(poses))
    assert fresh.segment is not first_segment and fresh_target.name != first_target.name
    ok, reply = call(session, proc.rpc_key, _step(poses, fresh_target))
    assert segments.check(fresh, proc.worker_id, reply) == (True, "")
    assert fresh.obs["depth"].shape == (7, 1, 24, 32) and segments.release(fresh) == []


def test_aggregator_steps_through_segments_and_leaves_no_file_after_kill_and_close():
    agg = make_aggregator(pool={"respawn": True}).start()
    run = agg.run_id
    try:
        poses = spawn_poses(agg)
        obs = agg.observe(poses)
        np.testing.assert_allclose(obs.images["depth"], reference(agg, poses)["depth"], atol=1e-4)
        mapped = {h["worker_id"]: set(h["image_segments"]) for h in agg.health()}
        # one segment per step, shared by the workers, each writing its own rows
        assert sorted(mapped) == agg.workers and len(set.union(*mapped.values())) == 1
        assert _shm_files(run) == []  # unlinked once each worker answered
        victim, pid = next(iter(agg.local_worker_pids().items()))
        os.kill(pid, signal.SIGKILL)
        assert _shm_files(run) == []
        assert wait_for(lambda: victim not in agg.workers, timeout=10.0)
        assert wait_for(lambda: not agg.observe(poses).lost.any() and len(set(agg.assignment().values())) == 2
                        and not agg.background_busy(), timeout=60.0, interval=0.2)
        again = agg.observe(poses)
        np.testing.assert_array_equal(again.images["depth"], obs.images["depth"])
        (newcomer,) = set(agg.workers) - set(mapped)
        (fresh,) = [set(h["image_segments"]) for h in agg.health() if h["worker_id"] == newcomer]
        assert fresh  # the replacement writes in place too (it opens the learner's descriptors)
        assert _shm_files(run) == []
    finally:
        agg.close()
    assert _shm_files(run) == []


def _links(fd_dir: str) -> list[tuple[str, str]]:
    """``(path, target)`` of each descriptor in ``fd_dir`` (one closed while listing is left out)."""
    out = []
    for fd in os.listdir(fd_dir):
        try:
            out.append((os.path.join(fd_dir, fd), os.readlink(os.path.join(fd_dir, fd))))
        except FileNotFoundError:
            continue
    return out


def test_observing_goes_on_while_another_process_tries_to_truncate_the_learners_segments():
    """What a process of the user finds of a live learner (its descriptors in /proc) it cannot
    resize: the learner reads on, with its images in place."""
    with make_aggregator() as agg:
        poses = spawn_poses(agg)
        first = agg.observe(poses)
        depth = first.images["depth"].copy()
        segments = [path for path, link in _links(f"/proc/{os.getpid()}/fd")
                    if link.startswith(f"/memfd:visfly-img-{agg.run_id}-")]
        assert segments
        for path in segments:
            resizer = subprocess.run([sys.executable, "-c", RESIZER, path], capture_output=True, text=True,
                                     timeout=60, cwd=REPO)
            assert resizer.returncode == 0 and "succeeded" not in resizer.stdout, resizer.stdout + resizer.stderr
        np.testing.assert_array_equal(first.images["depth"], depth)
        for _ in range(3):
            obs = agg.observe(poses)
            assert not obs.lost.any()
            np.testing.assert_array_equal(obs.images["depth"], depth)
        assert all(h["image_segments"] for h in agg.health())  # still written in place


class _SeenFromAnotherPidNamespace:
    """``os`` for :mod:`image_shm`, whose ``getpid`` is another process's: what a worker in another pid
    namespace (a container) finds at ``/proc/<pid>/fd/<fd>``."""

    def __init__(self, pid: int) -> None:
        self._pid = pid

    def getpid(self) -> int:
        return self._pid

    def __getattr__(self, name: str):
        return getattr(os, name)


def test_workers_that_cannot_reach_the_learners_descriptors_step_inline(monkeypatch):
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    try:
        monkeypatch.setattr(image_shm, "os", _SeenFromAnotherPidNamespace(sleeper.pid))
        with make_aggregator(pool={"num_local_workers": 1}, scenes={"num_scenes": 2}) as agg:
            monkeypatch.undo()
            poses = spawn_poses(agg)
            for _ in range(2):
                obs = agg.observe(poses)
                np.testing.assert_allclose(obs.images["depth"], reference(agg, poses)["depth"], atol=1e-4)
                assert not obs.lost.any()
            (health,) = agg.health()
            assert health["image_segments"] == {}
    finally:
        sleeper.kill()
        sleeper.wait()


# A learner that cannot open one more descriptor (RLIMIT_NOFILE of 0 once everything is imported).
NO_DESCRIPTORS = r"""
import resource
from visfly_dist.aggregator.image_shm import ImageSegments
from visfly_dist.protocol.cameras import CameraSpec

segments = ImageSegments("nofd", (CameraSpec(name="depth", kind="depth", width=32, height=24),))
resource.setrlimit(resource.RLIMIT_NOFILE, (0, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))
print(segments.offer([("w", 1)], 4, 0), segments.offer([("w", 1)], 4, 0), segments.live())
"""


def test_no_room_for_a_segment_means_inline_images():
    out = subprocess.run([sys.executable, "-c", NO_DESCRIPTORS], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert out.returncode == 0 and out.stdout.split() == ["None", "None", "[]"], out.stdout + out.stderr
    assert "cannot create an image segment" in out.stderr


@pytest.mark.parametrize("keep", [
    lambda a: a,                                  # the observation's array itself
    lambda a: a[1:, 0],                           # a slice of it
    lambda a: torch.from_numpy(a),                # a torch tensor over it
    lambda a: torch.from_numpy(a)[2:].view(-1),   # a view of that tensor
    lambda a: torch.from_numpy(a).numpy()[3],     # numpy over the tensor
    lambda a: {"obs": [a.reshape(-1)]},           # deep in a container
])
def test_a_held_observation_is_never_written_over_and_a_released_segment_is_reused(keep):
    segments = ImageSegments(RUN, CAMS)
    step = segments.offer([("w", 1)], 4, 0)
    first = step.segment
    step.obs["depth"][:] = 1.0  # what the worker writes
    kept = keep(step.obs["depth"])
    extra = [kept, kept]  # more references change nothing: ownership is the lease, not a count
    assert segments.release(step) == []
    del step
    later = []
    for value in range(2, 2 + image_shm.MAX_SEGMENTS + 2):  # more steps than segments, every one held
        other = segments.offer([("w", 1)], 4, 0)
        assert other.segment is not first
        other.obs["depth"][:] = value
        segments.release(other)
        later.append((value, other.obs["depth"]))
        del other
    assert (np.frombuffer(first.mm, np.float32, 4 * 24 * 32, first.blocks["depth"]) == 1.0).all()
    assert all((depth == value).all() for value, depth in later)
    del later
    gc.collect()
    live = segments.live()
    free = segments.offer([("w", 1)], 4, 0)  # the later ones are free again: one is reused, none made
    assert free.segment.name in live and segments.live() == live
    segments.release(free)
    del free, kept, extra
    segments.close()
    assert _shm_files(RUN) == []


def test_a_caller_that_says_it_holds_n_observations_cycles_through_the_same_segments():
    """A trainer keeping a rollout of ``n`` observations (``hold(n)``): once it lets go of its oldest
    each step, the segment comes back and no new one is made, even as the spawn rows of a step vary
    (a segment is made with room for the most any step asked for); without ``hold`` the held ones are
    retired and a new segment is made every step."""
    for held, new_each_step in ((16, False), (0, True)):
        segments = ImageSegments(RUN, CAMS)
        if held:
            segments.hold(held)
        kept: list[np.ndarray] = []
        made = set()
        for value in range(3 * 16):
            step = segments.offer([("w", 1)], 4, (0, 3, 9, 1, 5)[value % 5])  # a few next starts each step
            step.obs["depth"][:] = value
            segments.release(step)
            made.add(step.segment.name)
            kept.append(step.obs["depth"])
            del step
            if len(kept) > 16:  # the rollout replaces its oldest observation
                kept.pop(0)
        assert all((depth == value).all() for value, depth in zip(range(32, 48), kept))  # none written over
        assert (len(made) > 40) == new_each_step and (len(made) <= 16 + 4 or new_each_step)
        del kept
        gc.collect()
        segments.close()
    assert _shm_files(RUN) == []


def test_only_images_taken_in_place_count_as_written_over():
    """A worker that wrote into a segment before and whose request now got no reply did not write
    over anything (it failed already: reporting it would drop a worker the lost-request policy keeps)."""
    segments = ImageSegments(RUN, CAMS)

    def written(step):
        target = segments.target(step, ("w", 1), [0], [])
        SEQ.pack_into(step.segment.mm, target.seq_offset, target.seq)  # what the worker does after its images
        assert segments.check(step, "w", {"images_in_segment": True}) == (True, "")
        return target

    first = segments.offer([("w", 1)], 4, 0)
    written(first)
    segment = first.segment
    assert segments.release(first) == []
    del first
    unanswered = segments.offer([("w", 1)], 4, 0)
    assert unanswered.segment is segment
    segments.target(unanswered, ("w", 1), [0], [])  # sent, and no reply came
    assert segments.release(unanswered, failed=True) == []
    del unanswered
    late = segments.offer([("w", 1)], 4, 0)  # the failed step's segment was retired: a new one
    assert late.segment is not segment
    target = written(late)
    SEQ.pack_into(late.segment.mm, target.seq_offset, 0)  # a late write began after the reply was read
    assert segments.release(late) == ["w"]
    segments.close()
    assert _shm_files(RUN) == []


def test_a_segment_grows_by_a_new_file_and_keeps_room_for_varying_rows():
    segments = ImageSegments(RUN, CAMS)
    first = segments.offer([("w", 1)], 9, 3)
    first_segment = first.segment
    assert (first_segment.obs_rows, first_segment.spawn_rows) == (16, 4)
    assert segments.release(first) == []
    del first
    again = segments.offer([("w", 1)], 16, 4)  # room for 16 rows was made for 9
    newcomer = segments.offer([("v", 1)], 1, 0)  # the first one is busy: a new one
    assert again.segment is first_segment and newcomer.segment is not first_segment
    segments.release(again), segments.release(newcomer)
    del again, newcomer
    bigger = segments.offer([("w", 1)], 17, 0)
    assert bigger.segment is not first_segment and bigger.segment.name != first_segment.name
    assert segments.live() == [bigger.segment.name] and first_segment.fd == -1  # the small ones were closed
    segments.close()
    assert _shm_files(RUN) == []


def test_a_worker_without_shared_memory_refuses_segments(worker_factory):
    proc = worker_factory(RUN, shm=False)
    segments = ImageSegments(RUN, CAMS)
    with client_session(proc.endpoint, shm=False) as session:
        assert call(session, proc.rpc_key, LoadScene("a", "gen:pillars?seed=4", CAMS).to_message(), timeout=60.0)[0]
        lease = segments.offer([(proc.worker_id, 1)], 2, 0)
        target = segments.target(lease, (proc.worker_id, 1), [0], [])
        poses = _poses(2)
        ok, reply = call(session, proc.rpc_key, StepRequest((ScenePoses("a", poses),), image_segment=target)
                         .to_message())
        assert ok and "--no-shm" in reply["segment_refused"] and reply["images"]["depth"].shape == (2, 1, 24, 32)
        assert segments.check(lease, proc.worker_id, reply) == (False, "") and segments.release(lease) == []
        assert segments.offer([(proc.worker_id, 1)], 2, 0) is None
    segments.close()
