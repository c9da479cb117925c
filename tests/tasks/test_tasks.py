"""Every task: builds through make_env, steps with random actions, finite rewards, obs match spaces."""

import numpy as np
import pytest
import torch

from visfly_dist import make_env
from visfly_dist.errors import ConfigError
from visfly_dist.tasks import TASKS
from visfly_dist.tasks.gap_crossing import GapCrossingConfig
from visfly_dist.tasks.landing import LandingConfig, pad_in_image
from visfly_dist.tasks.common import forward_axis, obstacle_terms, target_observation
from tests.tasks.helpers import hover, place


@pytest.mark.parametrize("name", list(TASKS))
def test_task_steps_with_random_actions(envs, name):
    env = envs(name)
    num_envs = env.num_envs
    obs = env.reset()
    space = env.observation_space
    for _ in range(12):
        actions = np.stack([env.action_space.sample() for _ in range(num_envs)])
        obs, reward, done, infos = env.step(actions)
        assert reward.shape == (num_envs,) and np.all(np.isfinite(reward))
        assert set(obs) == set(space.spaces)
        for key, sub in space.spaces.items():
            assert obs[key].shape == (num_envs, *sub.shape) and obs[key].dtype == sub.dtype, key
            assert np.all(np.isfinite(obs[key])), key
        for info in infos:
            assert {"is_success", "collision", "out_of_bounds", "TimeLimit.truncated"} <= set(info)


def test_make_env_rejects_unknown_names_and_settings():
    with pytest.raises(ConfigError, match="unknown task 'flip'; valid tasks: navigation, hover, landing"):
        make_env("flip")
    with pytest.raises(ConfigError, match=r"unknown setting\(s\) \['gravity'\] for task 'hover'"):
        make_env("hover", gravity=3.0)
    with pytest.raises(ConfigError, match="num_envs=4 must be divisible by agents_per_scene=3"):
        make_env("gap_crossing", num_envs=4)


def test_task_defaults_are_valid_and_sized_for_a_small_machine():
    for name in TASKS:
        from visfly_dist.tasks import task_class

        cfg = task_class(name).config_class()
        cfg.validate()
        assert cfg.num_envs <= 16 and cfg.pool.num_local_workers == 2
    assert GapCrossingConfig().agents_per_scene == 3
    from visfly_dist.tasks.navigation import NavigationConfig

    assert NavigationConfig().scenes == ("gen:garage-stones?density=0.15",)
    assert NavigationConfig(density=0.3).scenes == ("gen:garage-stones?density=0.3",)
    assert LandingConfig().cameras[0].rotation[2] > 0.7


def test_pad_in_image_finds_the_dark_square():
    rgb = torch.full((2, 3, 20, 20), 150, dtype=torch.uint8)
    rgb[0, :, 0:4, 16:20] = 0  # top-right corner
    u, v, frac = pad_in_image(rgb, 40.0).T
    assert u[0].item() == pytest.approx(0.8) and v[0].item() == pytest.approx(-0.8)
    assert frac[0].item() == pytest.approx(16 / 400) and frac[1].item() == 0 and u[1].item() == 0


def test_hover_holds_at_the_target_for_a_good_reward(envs):
    env = envs("hover")
    env.reset()
    assert env.target.tolist() == [[1.0, 0.0, 1.5]] * 2  # gen:empty's metadata goal, not config.target
    place(env, [[1.0, 0.0, 1.5], [1.0, 0.0, 1.5]])
    _, reward, done, _ = env.step(hover(env))
    assert not done.any() and np.all(reward > 0.95)
    place(env, [[1.0, 0.0, 1.5], [1.0, 0.0, 4.0]])  # 2.5 m away: beyond max_distance
    _, reward, done, infos = env.step(hover(env))
    assert done.tolist() == [False, True] and infos[1]["TimeLimit.truncated"] is False and infos[1]["out_of_bounds"]
    assert reward[1] < -9


def test_landing_camera_looks_down_at_the_pad(envs):
    env = envs("landing")
    env.reset()
    assert env.pad[0].tolist() == [2.0, 0.0, 0.0]
    place(env, [[2.0, 0.0, 1.5], [4.5, 0.0, 1.5]])  # above the pad; 2.5 m beside it
    obs, _, _, _ = env.step(hover(env))
    u, v, frac = obs["pad"][0]
    assert abs(u) < 0.15 and abs(v) < 0.15 and frac > 0.01
    assert obs["pad"][1, 2] == 0
    place(env, [[2.0, 0.0, 0.15], [4.5, 0.0, 1.5]])  # resting just above the pad: success
    _, reward, done, infos = env.step(hover(env))
    assert infos[0]["is_success"] is True and done[0] and reward[0] > 5


def test_gap_crossing_targets_lanes_and_team_success(envs):
    env = envs("gap_crossing")
    obs = env.reset()
    assert env.target[:, 1].tolist() == [-2.0, 0.0, 2.0]
    assert obs["teammates"].shape == (3, 2, 6)
    assert np.all(np.abs(obs["state"][:, 1]) <= 0.51)  # spawned in the own lane
    place(env, [[7.0, -2.0, 1.5], [9.5, 0.0, 1.5], [12.0, 2.0, 1.5]])  # one is not through yet
    _, _, done, _ = env.step(hover(env))
    assert not done.any()
    place(env, [[9.5, -2.0, 1.5], [9.5, 0.0, 1.5], [9.5, 2.0, 1.5]])
    _, _, done, infos = env.step(hover(env))
    assert done.all() and all(info["is_success"] for info in infos)


def test_racing_counts_gates_in_order(envs):
    env = envs("racing")
    env.reset()
    gates = env.config.gates
    place(env, [gates[0], gates[1]])  # agent 1 at gate 1 while gate 0 is next: no pass
    obs, reward, _, _ = env.step(hover(env))
    assert obs["progress"][:, 0].tolist() == [0.25, 0.0]
    assert reward[0] > 0.5 and reward[1] < 0.5
    np.testing.assert_allclose(obs["state"][0, :3], np.subtract(gates[0], gates[1]), atol=0.05)


def test_navigation_shared_geometry_matches_the_formulas_across_resets(envs):
    """The hooks share one goal geometry per state: it must follow steps, resets and goal changes."""
    env = envs("navigation")
    env.reset()
    rng = np.random.default_rng(3)
    for step in range(6):
        env.step(rng.uniform(-0.3, 0.3, (env.num_envs, 4)).astype(np.float32) + hover(env))
        if step == 2:
            env.goal = env.goal + torch.tensor([0.0, 1.0, 0.0])  # a new goal object: the cache must follow it
        if step == 3:
            env.reset_some(np.array([True, False]))
        s, cfg = env.state, env.config
        distance = (s.pos - env.goal).norm(dim=1)
        torch.testing.assert_close(env.get_observation()["target"], target_observation(s.pos, s.quat, env.goal))
        assert torch.equal(env.get_success(), distance < cfg.success_radius)
        proximity, approach = obstacle_terms(s.pos, s.vel, env.frame.nearest, env.frame.distance, cfg.search_radius)
        heading = (forward_axis(s.quat) * (env.goal - s.pos) / distance[:, None]).sum(dim=1)
        expected = (-0.002 * s.vel.norm(dim=1) - 0.002 * s.omega.norm(dim=1) - 0.01 * proximity
                    + 0.05 * (env._prev_distance - distance) / cfg.ctrl_dt + 0.01 * heading - 0.05 * approach
                    + cfg.success_bonus * env.success.float() - cfg.fail_penalty * env.failure.float())
        torch.testing.assert_close(env.get_reward(), expected)
