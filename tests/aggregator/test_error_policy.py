"""What each error code of a load does to a run, with real workers: ``scene_error`` drops the source
(the run goes on while sources remain), ``overloaded`` backs off from that worker."""

from __future__ import annotations

import contextlib
import subprocess
import sys
import time
from typing import Iterator

import numpy as np
import pytest

from tests.aggregator.conftest import make_aggregator, spawn_poses
from tests.helpers import REPO, _read_line, free_port, start_worker, stop_process
from visfly_dist.errors import ConfigError, NoWorkersError, RemoteError

BAD = "gen:garage-stones?density=3"  # passes the config check; every worker refuses it (density <= 1)


def test_a_source_that_cannot_load_is_dropped_and_the_run_goes_on():
    agg = make_aggregator(pool={"num_local_workers": 1},
                          scenes={"sources": ("gen:pillars", BAD), "num_scenes": 3, "agents_per_scene": 2,
                                  "shuffle": False})
    with agg:
        assert list(agg.dataset.dropped) == [BAD] and "density=3" in agg.dataset.dropped[BAD]
        assert all(agg.slot_source(i).startswith("gen:pillars?") for i in range(agg.num_scenes))
        assert set(agg.assignment().values()) == {"local-0"}
        assert not agg.observe(spawn_poses(agg)).lost.any()


def test_a_run_whose_every_source_fails_to_load_fails_at_start_naming_them():
    agg = make_aggregator(pool={"num_local_workers": 1},
                          scenes={"sources": (BAD, "gen:pillars?density=9"), "num_scenes": 2, "agents_per_scene": 1})
    with pytest.raises(ConfigError, match=r"no scene source can be loaded: 'gen:garage-stones\?density=3': .*density=3.*"
                                          r"'gen:pillars\?density=9': .*density=9"):
        agg.start()


def test_an_overloaded_worker_gets_no_new_scene_for_a_while_and_the_others_take_it(scene_root):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = subprocess.Popen([sys.executable, "-m", "visfly_dist.cli", "router", "--listen", endpoint], cwd=REPO,
                              stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    workers = []
    try:
        assert "router ready" in _read_line(router, 30.0)
        workers = [start_worker("full", endpoint, scene_root, connect=True, worker_id="wa",
                                extra_args=["--max-scenes", "1"]),
                   start_worker("full", endpoint, scene_root, connect=True, worker_id="wb")]
        with make_aggregator(pool={"connect": (endpoint,), "num_local_workers": 0, "run_id": "full", "min_workers": 2},
                             scenes={"sources": ("gen:pillars",), "num_scenes": 3, "agents_per_scene": 2}) as agg:
            # Placement asked wa for two scenes (wa, wb, wa); it took one and refused the other.
            assert sorted(agg.assignment().values()) == ["wa", "wb", "wb"]
            poses = spawn_poses(agg)
            end = time.monotonic() + 2.5  # past the first backoff (1 s): nothing moves back onto the full worker
            while time.monotonic() < end:
                assert not agg.observe(poses).lost.any()
            assert {h["worker_id"]: len(h["scenes"]) for h in agg.health()} == {"wa": 1, "wb": 2}
            assert np.array_equal(np.sort(list(agg.assignment().values())), ["wa", "wb", "wb"])
    finally:
        for proc in workers:
            stop_process(proc)
        stop_process(router)


@contextlib.contextmanager
def _routed_worker(run_id: str, scene_root, worker_id: str, extra_args: list[str]) -> Iterator[str]:
    """A router and one worker joined to it, started with ``extra_args`` (its limits); yields the endpoint."""
    with _routed_workers(run_id, {worker_id: scene_root}, extra_args) as endpoint:
        yield endpoint


@contextlib.contextmanager
def _routed_workers(run_id: str, roots: dict, extra_args: tuple[str, ...] | list[str] = ()) -> Iterator[str]:
    """A router and a worker per entry of ``roots`` (worker id -> its scene root) joined to it;
    yields the endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = subprocess.Popen([sys.executable, "-m", "visfly_dist.cli", "router", "--listen", endpoint], cwd=REPO,
                              stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    workers = []
    try:
        assert "router ready" in _read_line(router, 30.0)
        for worker_id, root in roots.items():
            workers.append(start_worker(run_id, endpoint, root, connect=True, worker_id=worker_id,
                                        extra_args=list(extra_args)))
        yield endpoint
    finally:
        for worker in workers:
            stop_process(worker)
        stop_process(router)


def test_a_start_up_whose_every_worker_stays_full_fails_within_the_startup_timeout(scene_root):
    with _routed_worker("stuck", scene_root, "wa", ["--max-scenes", "1"]) as endpoint:
        agg = make_aggregator(pool={"connect": (endpoint,), "num_local_workers": 0, "run_id": "stuck",
                                    "startup_timeout_s": 3.0},
                              scenes={"sources": ("gen:pillars",), "num_scenes": 2, "agents_per_scene": 1})
        began = time.monotonic()
        with pytest.raises(NoWorkersError, match=r"1 scene slot\(s\) could not be placed within startup_timeout_s=3: "
                                                 r"every live worker backs off \(wa is full \(.*max-scenes"):
            with agg:
                pass
        assert time.monotonic() - began < 20.0  # the back-off doubles to 30 s: without a deadline, half an hour


def _garage_file(path, blocked: bool) -> str:
    """A floor with a ceiling triangle (the flight box) and a pillar; ``blocked``: a closed block
    filling the spawn region too."""
    import trimesh

    floor = trimesh.Trimesh([[-2, -5, 0], [12, -5, 0], [12, 5, 0], [-2, 5, 0], [0, 0, 4], [1, 0, 4], [0, 1, 4]],
                            [[0, 1, 2], [0, 2, 3], [4, 5, 6]])
    parts = [floor, trimesh.creation.box((1, 1, 2), trimesh.transformations.translation_matrix((8, 0, 1)))]
    if blocked:
        parts.append(trimesh.creation.box((2, 6, 3), trimesh.transformations.translation_matrix((1, 0, 1.5))))
    trimesh.util.concatenate(parts).export(path)
    return path.name


def test_a_swapped_in_scene_with_no_room_to_start_is_dropped_naming_it_and_the_run_goes_on(tmp_path, caplog):
    good, blocked = _garage_file(tmp_path / "good.ply", False), _garage_file(tmp_path / "blocked.ply", True)
    spec = ("uniform", (1.0, -2.0, 0.5), (1.0, 2.0, 2.5), 0.5)  # navigation's spawn box
    with make_aggregator(pool={"num_local_workers": 1, "scene_roots": (str(tmp_path),)},
                         scenes={"sources": (good, blocked), "num_scenes": 1, "agents_per_scene": 1,
                                 "swap_every_resets": 1, "shuffle": False}) as agg:
        assert agg.slot_source(0) == good
        poses = np.zeros((1, 7))
        poses[0, :3], poses[0, 3] = agg.sample_spawn(np.array([0]), *spec)[0], 1.0
        with caplog.at_level("WARNING", logger="visfly_dist.aggregator.scene_moves"):
            agg.note_resets(np.array([0]))  # due: the next source (blocked) loads in the background
            end = time.monotonic() + 60.0
            while blocked not in agg.dataset.dropped and time.monotonic() < end:
                assert not agg.observe(poses).lost.any()  # steps go on while the swap loads and fails
                time.sleep(0.05)
        assert "found only 0 of" in agg.dataset.dropped[blocked]
        assert any(f"scene source {blocked!r} cannot be used" in r.getMessage() for r in caplog.records)
        assert agg.slot_source(0) == good and not agg.take_next_scene().any()  # no swap was armed
        for _ in range(3):  # later swaps draw from what is left of the dataset
            agg.note_resets(np.array([0]))
            assert agg.sample_spawn(np.array([0]), *spec).shape == (1, 3)
            assert not agg.observe(poses).lost.any()


def test_a_scene_in_use_with_no_room_to_start_fails_the_first_reset_naming_it(tmp_path):
    blocked = _garage_file(tmp_path / "blocked.ply", True)
    with make_aggregator(pool={"num_local_workers": 1, "scene_roots": (str(tmp_path),)},
                         scenes={"sources": (blocked,), "num_scenes": 1, "agents_per_scene": 1}) as agg:
        with pytest.raises(RemoteError, match=r"sampling spawn positions in 'blocked.ply' \(slot 0\): found only 0 of"):
            agg.sample_spawn(np.array([0]), "uniform", (1.0, -2.0, 0.5), (1.0, 2.0, 2.5), 0.5)


def test_a_step_over_a_workers_pixel_bound_fails_at_the_first_observation(scene_root):
    """``too_large`` is the run's configuration against the workers' bounds: it fails at once (the env's
    reset), not somewhere in training."""
    with _routed_worker("big", scene_root, "small", ["--max-pixels", "1000"]) as endpoint:  # 32 x 24 depth: 768 pixels an agent
        with make_aggregator(pool={"connect": (endpoint,), "num_local_workers": 0, "run_id": "big"},
                             scenes={"sources": ("gen:pillars",), "num_scenes": 1, "agents_per_scene": 2}) as agg:
            with pytest.raises(RemoteError, match=r"step asks for 1536 pixels .* over this worker's bound of 1000") as err:
                agg.observe(np.tile(np.array([[2.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]], np.float32), (2, 1)))
            assert err.value.code == "too_large"


def test_a_file_one_worker_lacks_is_placed_on_the_worker_that_has_it(tmp_path, caplog):
    """``scene_missing`` is one worker's: the source stays in the dataset and goes to the workers that
    have its file (the run used to drop it everywhere, and failed when that was every source)."""
    full, partial = tmp_path / "full", tmp_path / "partial"
    full.mkdir(), partial.mkdir()
    both, only_full = _garage_file(full / "both.ply", False), _garage_file(full / "only_full.ply", False)
    _garage_file(partial / "both.ply", False)
    with _routed_workers("lacks", {"wa": full, "wb": partial}) as endpoint:
        with caplog.at_level("WARNING", logger="visfly_dist.aggregator.scene_moves"):
            with make_aggregator(pool={"connect": (endpoint,), "num_local_workers": 0, "run_id": "lacks", "min_workers": 2,
                                       "scene_roots": (str(full),)},  # the trainer sees every file
                                 scenes={"sources": (both, only_full), "num_scenes": 4, "agents_per_scene": 1,
                                         "shuffle": False}) as agg:
                assert not agg.dataset.dropped
                sources = {i: agg.slot_source(i) for i in range(agg.num_scenes)}
                assert sorted(sources.values()) == [both, both, only_full, only_full]
                poses, end = spawn_poses(agg), time.monotonic() + 30.0
                while "wb" not in agg.assignment().values() and time.monotonic() < end:
                    assert not agg.observe(poses).lost.any()  # the rebalance gives wb what it has
                assignment = agg.assignment()
                assert sorted(assignment.values()) == ["wa", "wa", "wb", "wb"]
                assert all(assignment[i] == "wa" for i, source in sources.items() if source == only_full)
        assert "worker wb has no 'only_full.ply' under its scene roots" in caplog.text


def test_a_file_no_worker_has_is_dropped_naming_every_worker(tmp_path):
    root_a, root_b, trainer = tmp_path / "a", tmp_path / "b", tmp_path / "trainer"
    for root in (root_a, root_b, trainer):
        root.mkdir()
        good = _garage_file(root / "good.ply", False)
    _garage_file(trainer / "nowhere.ply", False)  # the trainer has it, no worker does
    with _routed_workers("none", {"wa": root_a, "wb": root_b}) as endpoint:
        with make_aggregator(pool={"connect": (endpoint,), "num_local_workers": 0, "run_id": "none", "min_workers": 2,
                                   "scene_roots": (str(trainer),)},
                             scenes={"sources": (good, "nowhere.ply"), "num_scenes": 2, "agents_per_scene": 1,
                                     "shuffle": False}) as agg:
            assert list(agg.dataset.dropped) == ["nowhere.ply"]
            assert "no live worker has it: ['wa', 'wb']" in agg.dataset.dropped["nowhere.ply"]
            assert all(agg.slot_source(i) == good for i in range(agg.num_scenes))
