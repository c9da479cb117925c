"""Observations from two real workers: assembled in agent order, equal to an in-process render."""

from __future__ import annotations

import numpy as np

from tests.helpers import wait_for
import pytest

from tests.aggregator.conftest import CAMERAS, make_aggregator, pid_alive, reference, spawn_poses
from visfly_dist.protocol import UnloadScene


@pytest.fixture(scope="module")
def agg():
    with make_aggregator() as a:
        yield a


@pytest.fixture(scope="module")
def poses(agg):
    return spawn_poses(agg)


def test_scenes_are_balanced_and_distinct(agg):
    assert agg.num_agents == 12 and len(agg.workers) == 2
    assert agg.agent_scene.tolist() == [0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3]
    per_worker = [list(agg.assignment().values()).count(w) for w in agg.workers]
    assert per_worker == [2, 2]
    sources = [agg.slot_source(s) for s in range(4)]
    assert len(set(sources)) == 4 and all("seed=" in s for s in sources)
    health = agg.health()
    assert sorted(h["worker_id"] for h in health) == agg.workers
    assert sorted(s for h in health for s in h["slots"]) == [0, 1, 2, 3]


def test_observe_matches_in_process_render(agg, poses):
    obs = agg.observe(poses)
    ref = reference(agg, poses)
    depth = obs.images["depth"]
    assert depth.shape == (12, *CAMERAS[0].shape) and depth.dtype == np.float32
    np.testing.assert_allclose(depth, ref["depth"], atol=1e-4)
    np.testing.assert_array_equal(obs.collision, ref["collision"])
    np.testing.assert_allclose(obs.distance, ref["distance"], atol=1e-4)
    assert not obs.lost.any() and not obs.collision.any()
    assert obs.nearest.shape == (12, 3) and obs.inside.shape == (12,)
    for stage in ("fanout_s", "wait_s", "decode_s", "assemble_s", "render_s", "query_s", "transport_s"):
        assert obs.timings[stage] >= 0.0


def test_subset_comes_back_in_the_order_asked(agg, poses):
    full = agg.observe(poses)
    agents = np.array([11, 0, 5, 4])
    part = agg.observe(poses, agents)
    np.testing.assert_array_equal(part.images["depth"], full.images["depth"][agents])
    np.testing.assert_array_equal(part.distance, full.distance[agents])
    same = agg.observe(poses[agents], agents)  # (k, 7) rows of the agents only
    np.testing.assert_array_equal(same.images["depth"], part.images["depth"])


def test_spawn_positions_are_free_and_in_bounds(agg):
    pos = agg.sample_spawn(np.arange(12), "uniform", (2.0, -5.0, 1.0), (16.0, 5.0, 4.0), 0.5)
    bounds = agg.agent_bounds()
    assert bounds.shape == (12, 2, 3)
    assert np.all(pos >= bounds[:, 0]) and np.all(pos <= bounds[:, 1])
    poses = np.zeros((12, 7))
    poses[:, :3], poses[:, 3] = pos, 1.0
    obs = agg.observe(poses)
    assert not obs.collision.any() and np.all(obs.distance >= 0.5 - 1e-3)


def test_scene_metadata_comes_from_the_worker(agg):
    meta = agg.scene_metadata(0)
    assert meta["source"] == agg.slot_source(0)
    assert meta.get("kind") in ("garage-stones", "pillars")


def test_close_leaves_no_child_process():
    agg = make_aggregator(pool={"num_local_workers": 1}, scenes={"num_scenes": 1, "agents_per_scene": 1}).start()
    pids = list(agg.local_worker_pids().values())
    assert pids and all(pid_alive(p) for p in pids)
    agg.close()
    agg.close()  # idempotent
    assert not any(pid_alive(p) for p in pids)


def test_scenes_forgotten_by_a_worker_are_reloaded_in_the_background(agg, poses):
    before = agg.observe(poses)
    worker = agg.assignment()[1]
    slots = [s for s, w in agg.assignment().items() if w == worker]
    # As if the worker restarted under the same id between our liveliness check and the request.
    replies = agg._pool.call([(worker, UnloadScene(agg.table.slots[s].key).to_message()) for s in slots], 5.0)
    assert all(r.message["type"] == "ok" for r in replies)
    obs = agg.observe(poses)
    assert obs.lost.tolist() == np.isin(agg.agent_scene, slots).tolist()
    np.testing.assert_array_equal(obs.images["depth"], before.images["depth"])  # last good data meanwhile
    assert wait_for(lambda: not agg.observe(poses).lost.any(), timeout=30)
    np.testing.assert_array_equal(agg.observe(poses).images["depth"], before.images["depth"])
