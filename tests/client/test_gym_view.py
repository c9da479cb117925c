"""Gymnasium views: the VectorEnv (SAME_STEP) and the single-agent Env, checked by the libraries' checkers."""

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from gymnasium.vector import AutoresetMode, VectorEnv
from stable_baselines3.common.env_checker import check_env as sb3_check_env

from visfly_dist.errors import ConfigError

from tests.client.counter_task import make_counter


@pytest.fixture(scope="module")
def vec_env():
    env = make_counter(num_envs=2, max_episode_steps=3)
    yield env
    env.close()


@pytest.fixture(scope="module")
def one_env():
    env = make_counter(num_envs=1, max_episode_steps=4)
    yield env
    env.close()


def test_vector_view_properties(vec_env):
    view = vec_env.as_gymnasium()
    assert isinstance(view, VectorEnv) and view.num_envs == 2
    assert view.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    assert view.single_observation_space == vec_env.observation_space
    assert view.single_action_space == vec_env.action_space
    assert view.action_space.shape == (2, 4)
    assert view.observation_space["depth"].shape == (2, 1, 16, 16)


def test_vector_view_reset_step_and_same_step_autoreset(vec_env):
    view = vec_env.as_gymnasium(AutoresetMode.SAME_STEP)
    obs, info = view.reset(seed=5)
    assert view.observation_space.contains(obs) and info == {}
    again, _ = view.reset(seed=5)
    np.testing.assert_array_equal(obs["state"], again["state"])
    for t in range(1, 4):
        obs, reward, terminated, truncated, infos = view.step(view.action_space.sample())
        assert view.observation_space.contains(obs)
        assert reward.shape == (2,) and terminated.dtype == bool and truncated.dtype == bool
        if t < 3:
            assert not (terminated | truncated).any() and "final_obs" not in infos
    assert truncated.all() and not terminated.any()
    assert infos["_final_obs"].all() and infos["_final_info"].all()
    for i in range(2):
        final = infos["final_obs"][i]
        assert vec_env.observation_space.contains(final) and final["step"][0] == 3
        assert obs["step"][i, 0] == 0
    assert infos["final_info"]["is_success"].tolist() == [False, False]
    assert not [k for k in infos["final_info"] if "final" in k]  # the step's own infos, not the final entries
    assert view.render() is None  # no render mode, as Gymnasium's envs without one
    assert infos["collision"].shape == (2,) and infos["_collision"].all()


def test_single_agent_view_passes_gymnasium_and_sb3_checkers(one_env):
    view = one_env.as_gymnasium_env()
    assert isinstance(view, gymnasium.Env)
    gym_check_env(view, skip_close_check=True)
    sb3_check_env(view, warn=False, skip_render_check=True)  # its render check closes the env
    assert view.render() is None and one_env.get_images() == [None]


def test_single_agent_view_returns_the_terminal_observation(one_env):
    view = one_env.as_gymnasium_env()
    view.reset(seed=1)
    for t in range(1, 5):
        obs, reward, terminated, truncated, info = view.step(view.action_space.sample())
    assert truncated and not terminated and obs["step"][0] == 4 and np.isfinite(reward)


def test_single_agent_view_needs_one_agent(vec_env):
    with pytest.raises(ConfigError, match="needs num_envs=1, got num_envs=2"):
        vec_env.as_gymnasium_env()


def test_next_step_autoreset_returns_the_last_view_then_the_first(vec_env):
    view = vec_env.as_gymnasium()
    obs, _ = view.reset(seed=3)
    for t in range(1, 4):
        obs, reward, terminated, truncated, infos = view.step(view.action_space.sample())
    assert truncated.all() and obs["step"][:, 0].tolist() == [3, 3]  # the last observation, as Gymnasium's NEXT_STEP
    obs, reward, terminated, truncated, _ = view.step(view.action_space.sample())  # actions ignored: the reset step
    assert obs["step"][:, 0].tolist() == [0, 0] and reward.tolist() == [0.0, 0.0]
    assert not (terminated | truncated).any()
    start = obs["state"][:, :3].copy()
    obs, *_ = view.step(view.action_space.sample())
    assert obs["step"][:, 0].tolist() == [1, 1] and not np.allclose(obs["state"][:, :3], start)


def test_seed_lists_seed_every_sub_env_and_are_checked(vec_env):
    view = vec_env.as_gymnasium()
    a, _ = view.reset(seed=[1, 2])
    assert view.np_random_seed is not None and view.np_random_seed >= 0
    view.step(view.action_space.sample())  # a history in between changes nothing
    b, _ = view.reset(seed=[1, 2])
    c, _ = view.reset(seed=[1, 3])
    np.testing.assert_array_equal(a["state"], b["state"])
    np.testing.assert_array_equal(a["state"][0], c["state"][0])  # sub-env 0 follows its own seed only
    assert not np.array_equal(a["state"][1], c["state"][1])
    d, _ = view.reset(seed=1)  # an int s seeds sub-env i with s + i, as Gymnasium's vector envs do
    np.testing.assert_array_equal(a["state"], d["state"])
    assert view.np_random_seed == 1
    with pytest.raises(ValueError, match="one seed per sub-env: num_envs=2, got length 3"):
        view.reset(seed=[1, 2, 3])
    with pytest.raises(ValueError, match="non-negative int, got -1"):
        view.reset(seed=[1, -1])


def test_reset_mask_resets_only_the_masked_sub_envs(vec_env):
    view = vec_env.as_gymnasium()
    view.reset(seed=0)
    view.step(view.action_space.sample())
    obs, _ = view.reset(options={"reset_mask": np.array([False, True])})
    assert obs["step"][:, 0].tolist() == [1, 0]
    with pytest.raises(ValueError, match="reset_mask"):
        view.reset(options={"reset_mask": np.array([False, False])})


def test_a_seeded_masked_reset_is_reproducible_and_does_not_come_back(vec_env):
    view, mask = vec_env.as_gymnasium(), np.array([False, True])
    view.reset(seed=0)
    view.step(view.action_space.sample())
    x, _ = view.reset(seed=11, options={"reset_mask": mask})
    view.reset(seed=99)
    for _ in range(2):
        view.step(view.action_space.sample())
    y, _ = view.reset(seed=11, options={"reset_mask": mask})
    np.testing.assert_array_equal(x["state"][1], y["state"][1])  # the same seed, another history
    full, _ = view.reset(seed=[5, 12])
    np.testing.assert_array_equal(full["state"][1], x["state"][1])  # seed 11 gives sub-env 1 the seed 12
    again, _ = view.reset()  # an unseeded reset does not reuse the masked reset's seed
    assert not np.array_equal(again["state"], full["state"])


def test_gymnasium_vector_wrappers_accept_the_view(vec_env):
    from gymnasium.wrappers.vector import FilterObservation, FlattenObservation

    for wrapped in (FlattenObservation(vec_env.as_gymnasium()), FilterObservation(vec_env.as_gymnasium(), ["state"])):
        obs, _ = wrapped.reset(seed=0)
        for _ in range(4):
            obs, *_ = wrapped.step(wrapped.action_space.sample())
        assert wrapped.observation_space.contains(obs)
