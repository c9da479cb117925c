"""MultiDroneEnvBase: teams, teammates' observation, inter-drone collision, team resets, scene swaps."""

import numpy as np
import pytest
import torch

from visfly_dist.client import MultiDroneEnvBase
from visfly_dist.dynamics import QuadState

from tests.client.counter_task import CounterConfig, CounterTask, small_pool


class TeamTask(MultiDroneEnvBase, CounterTask):
    def get_observation(self):
        return {**super().get_observation(), "teammates": self.teammates_observation()}


@pytest.fixture(scope="module")
def env():
    env = TeamTask(CounterConfig(num_envs=4, agents_per_scene=2, max_episode_steps=50, pool=small_pool()))
    yield env
    env.close()


def hover(env):
    return np.tile(env.quad.hover_action().numpy(), (env.num_envs, 1))


def place(env, positions):
    pos = torch.tensor(positions, dtype=torch.float32)
    env.state = QuadState.where(torch.ones(env.num_envs, dtype=torch.bool), env.quad.initial_state(pos), env.state)


def test_teammates_are_the_other_agents_of_the_scene(env):
    assert env.config.multi_agent and env.teammates.tolist() == [[1], [0], [3], [2]]
    env.reset()
    place(env, [[0, 0, 2], [1, 0, 2], [0, 0, 2], [0, 2, 3]])
    obs, _, _, _ = env.step(hover(env))
    rel = obs["teammates"][:, 0, :3]
    assert obs["teammates"].shape == (4, 1, 6)
    np.testing.assert_allclose(rel, [[1, 0, 0], [-1, 0, 0], [0, 2, 1], [0, -2, -1]], atol=0.02)


def test_close_teammates_collide_and_the_team_resets_together(env):
    env.reset()
    place(env, [[0, 0, 2], [0.15, 0, 2], [0, 0, 2], [0, 2, 2]])  # team 0 closer than 2 * 0.1 m
    obs, _, done, infos = env.step(hover(env))
    assert done.tolist() == [True, True, False, False]
    assert infos[0]["TimeLimit.truncated"] is False and infos[1]["TimeLimit.truncated"] is False
    assert obs["step"][:, 0].tolist() == [0, 0, 1, 1]


def test_one_member_done_truncates_the_team(env):
    env.reset()
    place(env, [[0, 0, 2], [0, 1, 2], [0, 0, 2], [0, 1, 2]])  # no teammate collision, whatever the spawns
    env.force_success[2] = True
    try:
        obs, _, done, infos = env.step(hover(env))
    finally:
        env.force_success[:] = False
    assert done.tolist() == [False, False, True, True]
    assert infos[2]["is_success"] is True and infos[2]["TimeLimit.truncated"] is False
    assert infos[3]["TimeLimit.truncated"] is True
    assert obs["step"][2:, 0].tolist() == [0, 0] and obs["step"][:2, 0].tolist() == [1, 1]


def test_a_scene_swap_takes_over_at_each_agents_episode_end_and_cuts_no_episode():
    env = CounterTask(CounterConfig(num_envs=4, agents_per_scene=2, swap_every_resets=1, max_episode_steps=500,
                                    pool=small_pool()))
    with env:
        env.reset()
        place(env, [[0, 0, 2], [0, 1, 2], [0, 0, 2], [0, 1, 2]])
        sources = [env.aggregator.slot_source(s) for s in range(2)]
        env.force_success[0] = True
        _, _, done, infos = env.step(hover(env))
        env.force_success[:] = False
        assert done.tolist() == [True, False, False, False]  # agent 0 succeeded; slot 0's next scene loads meanwhile
        for _ in range(400):  # steps go on in the old scene; the new one is armed once loaded
            _, _, done, infos = env.step(hover(env))
            assert not done.any() and not any(info.get("swapped") for info in infos)
            if env.aggregator.table.slots[0].incoming is not None:
                break
        new = env.aggregator.table.slots[0].incoming.move.source
        for agent in (1, 0):  # each moves at its own episode end
            env.force_success[agent] = True
            obs, _, done, infos = env.step(hover(env))
            env.force_success[:] = False
            assert done.tolist() == [i == agent for i in range(4)] and infos[agent]["is_success"] is True
            assert env.aggregator.agent_sources()[agent] == new and obs["step"][agent, 0] == 0
            lo, hi = env.aggregator.table.slots[0].incoming.bounds if agent == 1 else env.aggregator.table.slots[0].bounds
            assert (env.bounds[agent].numpy() == np.stack([lo, hi]).astype(np.float32)).all()
        assert env.aggregator.slot_source(0) == new and env.aggregator.slot_source(1) == sources[1]
        assert env.aggregator.agent_sources() == [new, new, sources[1], sources[1]]
        assert obs["step"][2:, 0].min() > 1  # slot 1's episodes ran on
