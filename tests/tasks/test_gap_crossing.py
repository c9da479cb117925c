"""Gap crossing: a scripted team gets through with the task's own rules; eval counts teams."""

import numpy as np
import pytest

from visfly_dist import make_env
from visfly_dist.tasks.navigation import FORWARD_DEPTH
from visfly_dist.training.evaluation import evaluate
from tests.tasks.helpers import hover, place, small

LV_MAX_SPEED = 10.0  # the LV controller maps actions in [-1, 1] onto +-10 m/s


def scripted_velocities(env, step: int, speed: float = 2.5) -> np.ndarray:
    """LV actions flying each drone to the gap's mouth, through it and on to its own target.

    The middle lane goes first, the others 1.1 s apart, so the team queues through the one gap.
    """
    pos, actions = env.state.pos.detach().numpy(), np.zeros((env.num_envs, 4), np.float32)
    for i in range(env.num_envs):
        rank, target = int(env.team_rank[i]), env.target[i].numpy()
        gap_x, gap_y = float(env.gap_x[i]), float(env.gap_point[i, 1])
        if step * env.config.ctrl_dt < (0, 1, 2)[(rank + 2) % 3] * 1.1:  # middle (rank 1) first
            continue
        if pos[i, 0] < gap_x - 1.0 and abs(pos[i, 1] - gap_y) > 0.1:
            waypoint = np.array([gap_x - 1.0, gap_y, target[2]])
        elif pos[i, 0] < gap_x + 1.2:
            waypoint = np.array([gap_x + 1.5, gap_y, target[2]])
        else:
            waypoint = target
        delta = waypoint - pos[i]
        dist = max(float(np.linalg.norm(delta)), 1e-6)
        actions[i, :3] = delta / dist * min(speed, 3.0 * dist) / LV_MAX_SPEED
    return actions


def test_a_scripted_team_crosses_the_gap_with_the_tasks_rules():
    env = make_env("gap_crossing", num_envs=3, seed=3, controller="lv", **small((FORWARD_DEPTH,)))
    try:
        env.reset()
        rewards = []
        for step in range(env.config.max_episode_steps):
            _, reward, done, infos = env.step(scripted_velocities(env, step))
            rewards.append(reward)
            if done.any():
                break
        assert done.all() and all(info["is_success"] for info in infos), (step, infos)
        assert not any(info["collision"] for info in infos)
        assert np.sum(rewards, axis=0).min() > 10.0  # progress along the path and the team bonus
    finally:
        env.close()


def test_progress_pays_for_heading_to_the_gap_not_along_the_lane(envs):
    env = envs("gap_crossing")
    env.reset()
    place(env, [[7.0, -2.0, 1.5], [4.0, 0.0, 1.5], [7.0, 2.0, 1.5]])
    env.step(hover(env))
    before = env.path_distance().clone()
    toward_gap = np.array([7.0, 2.0]) + 0.3 * np.array([1.0, -2.0]) / np.sqrt(5.0)
    place(env, [[7.3, -2.0, 1.5], [4.0, 0.0, 1.5], [*toward_gap, 1.5]])  # 0.3 m along the lane / toward the gap
    gained = (before - env.path_distance()).numpy()
    assert gained[2] == pytest.approx(0.3, abs=1e-4) and 0.0 < gained[0] < 0.15
    place(env, [[9.0, -2.0, 1.5], [9.0, 0.0, 1.5], [9.0, 2.0, 1.5]])  # past the wall: straight to the target
    np.testing.assert_allclose(env.path_distance().numpy(), 4.0, atol=1e-5)


class TeleportPolicy:
    """Puts team 0 past the wall (team success) and one member of team 1 into the wall (collision)."""

    def __init__(self, env):
        self.env = env

    def predict(self, obs, deterministic=True):
        place(self.env, [[9.5, -2.0, 1.5], [9.5, 0.0, 1.5], [9.5, 2.0, 1.5],
                         [8.0, -2.0, 1.5], [2.0, 0.0, 1.5], [2.0, 2.0, 1.5]])
        return hover(self.env), None


def test_eval_counts_team_episodes():
    from stable_baselines3.common.vec_env import VecMonitor

    env = VecMonitor(make_env("gap_crossing", num_envs=6, seed=5, **small((FORWARD_DEPTH,))))
    try:
        stats = evaluate(TeleportPolicy(env.unwrapped), env, episodes=4)
    finally:
        env.close()
    assert stats.team_size == 3 and stats.episodes == 4
    assert sorted(e.agent for e in stats.episode_log) == [0, 0, 3, 3]
    assert stats.success_rate == pytest.approx(0.5)  # per agent it would be 6 of 12
    assert stats.end_causes["success"] == 2 and stats.end_causes["collision"] == 2 and stats.end_causes["swapped"] == 0
    assert "over 4 teams of 3" in stats.line()
