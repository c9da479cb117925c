"""Shared helpers of the aggregator tests: aggregators with real local worker processes."""

from __future__ import annotations

import os

import numpy as np

from visfly_dist.aggregator import Aggregator, PoolConfig, SceneSetConfig
from visfly_dist.protocol import CameraSpec

CAMERAS = (CameraSpec(name="depth", kind="depth", width=32, height=24),)
SEARCH_RADIUS = 5.0
DRONE_RADIUS = 0.1


def make_aggregator(pool: dict | None = None, scenes: dict | None = None, seed: int = 0) -> Aggregator:
    """An (unstarted) aggregator with raycast local workers and short deadlines."""
    pool_kw = dict(num_local_workers=2, backend="raycast", step_timeout_s=5.0, startup_timeout_s=60.0, lease_ms=1000)
    pool_kw.update(pool or {})
    scene_kw = dict(sources=("gen:garage-stones", "gen:pillars"), num_scenes=4, agents_per_scene=3)
    scene_kw.update(scenes or {})
    return Aggregator(PoolConfig(**pool_kw), SceneSetConfig(**scene_kw), CAMERAS, drone_radius=DRONE_RADIUS,
                      search_radius=SEARCH_RADIUS, seed=seed)


def spawn_poses(agg: Aggregator, seed: int = 0) -> np.ndarray:
    """``(N, 7)`` float32 poses at free positions with random yaw."""
    pos = agg.sample_spawn(np.arange(agg.num_agents), "uniform", (2.0, -5.0, 1.0), (16.0, 5.0, 4.0), 0.5)
    yaw = np.random.default_rng(seed).uniform(-np.pi, np.pi, agg.num_agents)
    poses = np.zeros((agg.num_agents, 7), np.float32)
    poses[:, :3] = pos
    poses[:, 3] = np.cos(yaw / 2)
    poses[:, 6] = np.sin(yaw / 2)
    return poses


def reference(agg: Aggregator, poses: np.ndarray) -> dict[str, np.ndarray]:
    """What the agents should see, computed in this process from the same sources and poses."""
    from visfly_dist.scene_worker.queries import ObstacleQueries
    from visfly_dist.scene_worker.render_base import make_renderer
    from visfly_dist.scenes import resolve_source

    n = agg.num_agents
    out = {"depth": np.zeros((n, *CAMERAS[0].shape), np.float32), "collision": np.zeros(n, bool),
           "distance": np.zeros(n, np.float32)}
    for slot in range(agg.num_scenes):
        idx = np.flatnonzero(agg.agent_scene == slot)
        scene = resolve_source(agg.slot_source(slot), [os.getcwd()])
        rows = poses[idx].astype(np.float64)
        out["depth"][idx] = make_renderer("raycast", scene, CAMERAS, drone_radius=DRONE_RADIUS).render(rows)["depth"]
        q = ObstacleQueries(scene, drone_radius=DRONE_RADIUS).query(rows[:, :3], SEARCH_RADIUS)
        out["collision"][idx] = q.collision
        out["distance"][idx] = q.distance
    return out


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True
