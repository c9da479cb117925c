"""Navigation among moving obstacles: the client's obstacle states, the worker's answers at the
env's simulation time, and the observation of the K nearest obstacles."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from tests.tasks.helpers import hover, place
from visfly_dist.errors import ConfigError
from visfly_dist.scene_worker.queries import ObstacleQueries
from visfly_dist.scenes import resolve_source
from visfly_dist.tasks.navigation_moving import MOVING_ROW, MovingNavigationConfig


def test_worker_answers_and_observation_follow_the_moving_stones(envs):
    env = envs("navigation_moving")
    env.reset()
    scenes = [resolve_source(env.scene_metadata(a)["source"], [os.getcwd()]) for a in range(env.num_envs)]
    assert all(len(scene.moving_objects) == 4 for scene in scenes)
    t_before = env.sim_time
    for _ in range(3):
        env.step(hover(env))
    assert env.sim_time == pytest.approx(t_before + 3 * env.config.ctrl_dt)
    # put each drone next to moving stone 0 of its scene where it will be, and step (hovering) once more
    t_next = env.sim_time + env.config.ctrl_dt
    stones = [scene.moving_objects[0] for scene in scenes]
    place(env, np.stack([s.motion.position(t_next) + [0.0, 0.0, s.bounding_radius + 0.4] for s in stones]))
    env.step(hover(env))
    assert env.sim_time == pytest.approx(t_next)
    positions = env.state.pos.detach().numpy().astype(np.float32).astype(np.float64)
    states = env.moving_states()   # positions, velocities and accelerations exposed to the task
    for agent, scene in enumerate(scenes):
        for j, obj in enumerate(scene.moving_objects):
            want_state = obj.motion.state(env.sim_time)
            np.testing.assert_allclose(states.position[agent, j].numpy(), want_state.position, atol=1e-5)
            np.testing.assert_allclose(states.acceleration[agent, j].numpy(), want_state.acceleration, atol=1e-5)
    assert bool(states.valid.all())
    obs = env.moving_observation()
    k = env.config.moving_nearest
    assert obs.shape == (env.num_envs, MOVING_ROW * k)
    rows = obs.reshape(env.num_envs, k, MOVING_ROW)
    state = env.state
    for agent, scene in enumerate(scenes):
        want = ObstacleQueries(scene.at_time(env.sim_time), drone_radius=env.config.drone_radius).query(
            positions[agent:agent + 1], env.config.search_radius)
        assert env.frame.distance[agent].item() == pytest.approx(want.distance[0], abs=1e-5)
        assert env.frame.distance[agent] < 0.5   # the stone, not the garage, is the nearest obstacle
        centres = np.stack([o.motion.position(env.sim_time) for o in scene.moving_objects])
        velocities = np.stack([o.motion.state(env.sim_time).velocity for o in scene.moving_objects])
        radii = np.array([o.bounding_radius for o in scene.moving_objects])
        order = np.argsort(np.linalg.norm(centres - positions[agent], axis=1) - radii)[:k]
        assert order[0] == 0
        rot = _rotation(state.quat[agent].detach().numpy().astype(np.float64))
        pos, vel = state.pos[agent].detach().numpy(), state.vel[agent].detach().numpy()
        np.testing.assert_allclose(rows[agent, :, :3].numpy(), (centres[order] - pos) @ rot, atol=1e-4)
        np.testing.assert_allclose(rows[agent, :, 3:6].numpy(), (velocities[order] - vel) @ rot, atol=1e-4)
        np.testing.assert_array_equal(rows[agent, :, 6].numpy(), 1.0)


def _rotation(q: np.ndarray) -> np.ndarray:
    """Body-to-world rotation matrix of a unit quaternion wxyz."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def test_fewer_obstacles_than_k_are_padded_with_invalid_rows(envs):
    env = envs("navigation_moving")
    config = env.config
    try:
        env.config = config.replace(moving_nearest=6)
        rows = env.moving_observation().reshape(env.num_envs, 6, MOVING_ROW)
        np.testing.assert_array_equal(rows[:, :4, 6].numpy(), 1.0)
        assert torch.all(rows[:, 4:] == 0)
    finally:
        env.config = config


def test_config_names_bad_moving_settings():
    with pytest.raises(ConfigError, match=r"moving=-1 must be an int in \[0, 100\]"):
        MovingNavigationConfig(moving=-1).validate()
    with pytest.raises(ConfigError, match=r"moving_nearest=0 must be an int in \[1, 32\]"):
        MovingNavigationConfig(moving_nearest=0).validate()
    assert MovingNavigationConfig(moving=3).scenes == ("gen:garage-stones?density=0.15&moving=3&moving_speed=1.0",)


def test_tiny_training_run(tmp_path):
    """A smoke test only: PPO trains a few hundred steps on the task through the CLI."""
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "visfly_dist.cli", "train", "navigation_moving", "--timesteps", "256",
                           "--checkpoint-every", "0", "--out", str(out), "--num-envs", "4", "--workers", "1",
                           "--n-steps", "32", "--batch-size", "64", "--set", "max_episode_steps=20",
                           "--set", "moving=3",
                           "--set", "cameras=[{\"name\": \"depth\", \"width\": 32, \"height\": 32, \"offset\": [0.2, 0, 0]}]"],
                          capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr
    assert (out / "final.zip").is_file() and "done: 256 steps" in proc.stdout
