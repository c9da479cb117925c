"""One round trip per step (resets included), and the EnvPool-style send/recv interface."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.client.counter_task import make_counter, small_pool
from visfly_dist.errors import ConfigError


@pytest.fixture(scope="module")
def env():
    env = make_counter(num_envs=4, max_episode_steps=3, pool=small_pool(workers=2))
    yield env
    env.close()


def _count_requests(env):
    """Count step requests sent to the workers (wrapping the aggregator's submit)."""
    calls = []
    submit = env.aggregator.submit

    def counting(*args, **kwargs):
        calls.append(kwargs.get("spawn_agents"))
        return submit(*args, **kwargs)

    env.aggregator.submit = counting
    return calls


def test_steps_with_resets_make_one_round_trip_each(env):
    env.reset()
    calls = _count_requests(env)
    observe = env.aggregator.observe
    env.aggregator.observe = lambda *a, **k: pytest.fail("a second round trip inside a step")
    try:
        hover = np.tile(env.quad.hover_action().numpy(), (4, 1))
        for t in range(7):  # episodes of 3 steps: resets at steps 3 and 6
            obs, _, done, infos = env.step(hover)
            if t in (2, 5):
                assert done.all() and obs["step"][:, 0].tolist() == [0, 0, 0, 0]
                assert all(info["terminal_observation"]["step"][0] == 3 for info in infos)
        assert len(calls) == 7
        # each reset agent's next start is rendered with the following step, ready before it is needed
        assert [len(c) for c in calls] == [4, 0, 0, 4, 0, 0, 4]  # after reset() too
    finally:
        del env.aggregator.submit
        env.aggregator.observe = observe


def test_reset_views_match_a_fresh_render_of_the_start(env):
    env.reset()
    hover = np.tile(env.quad.hover_action().numpy(), (4, 1))
    for _ in range(3):
        obs, _, done, _ = env.step(hover)
    assert done.all()
    fresh = env.aggregator.observe(env.state.pose().detach().numpy())  # where the agents now stand
    np.testing.assert_array_equal(obs["depth"], fresh.images["depth"])


def test_send_recv_returns_groups_and_matches_the_synchronous_step(env):
    env.reset()
    env.seed(7)
    env.reset()
    hover = torch.as_tensor(np.tile(env.quad.hover_action().numpy(), (2, 1)))
    env.send(hover, [0, 1])
    env.send(hover, [2, 3])
    with pytest.raises(ConfigError, match="still in flight"):
        env.send(hover, [1, 2])
    seen = []
    for _ in range(2):
        result, ids = env.recv()
        seen.append(sorted(ids.tolist()))
        assert result.observation["depth"].shape == (2, 1, 16, 16) and result.reward.shape == (2,)
        assert result.observation["step"][:, 0].tolist() == [1, 1]
    assert sorted(seen) == [[0, 1], [2, 3]]
    with pytest.raises(ConfigError, match="without a send"):
        env.recv()
    # group A runs ahead of group B: its episode ends first, B's rows are untouched
    env.send(hover, [0, 1])
    env.recv()
    env.send(hover, [0, 1])
    result, ids = env.recv()
    assert ids.tolist() == [0, 1] and result.truncated.all()
    assert env.episode_step.tolist() == [0, 0, 1, 1]
    for bad in ([4, 5], [1, 1], [-1, 0], [0.0, 1.0], []):  # out of range, repeated, negative, not ints, none
        with pytest.raises(ConfigError, match="distinct indices"):
            env.send(hover[:len(bad)], bad)
    with pytest.raises(ConfigError, match="without a send"):  # nothing was sent
        env.recv()


def test_a_reset_drops_the_groups_in_flight_and_a_step_refuses_them(env):
    env.seed(3)
    env.reset()
    hover = torch.as_tensor(np.tile(env.quad.hover_action().numpy(), (2, 1)))
    env.send(hover, [0, 1])
    with pytest.raises(ConfigError, match="step\\(\\) while 1 group"):
        env.step(np.tile(env.quad.hover_action().numpy(), (4, 1)))
    with pytest.raises(ConfigError, match="reset_some\\(\\) while 1 group"):
        env.reset_some(np.array([True, False, False, False]))
    obs = env.reset()  # the group in flight never happened
    assert env.episode_step.tolist() == [0, 0, 0, 0]
    with pytest.raises(ConfigError, match="without a send"):
        env.recv()
    fresh = env.aggregator.observe(env.state.pose().detach().numpy())  # where the agents now stand
    np.testing.assert_array_equal(obs["depth"], fresh.images["depth"])


def test_groups_stepped_in_turn_share_one_clock():
    env = make_counter(num_envs=4, max_episode_steps=50, pool=small_pool(workers=2))
    try:
        env.reset()
        hover = torch.as_tensor(np.tile(env.quad.hover_action().numpy(), (2, 1)))
        dt = env.config.ctrl_dt
        for k in range(1, 4):
            env.send(hover, [0, 1])
            env.send(hover, [2, 3])
            times = []
            for _ in range(2):
                env.recv()
                times.append(env.sim_time)
            assert times == pytest.approx([k * dt, k * dt])
    finally:
        env.close()
