"""The pipelined rollout (two agent groups in turn): the buffer's rows line up per agent, the groups
split every worker's scenes, and the groups share one simulation clock."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

from tests.client.counter_task import make_counter, small_pool
from visfly_dist.training.extractors import visfly_policy_kwargs
from visfly_dist.training.pipelined import PipelinedPPO, agent_groups


def test_groups_deal_out_each_workers_scenes():
    assignment = {0: "w0", 1: "w0", 2: "w0", 3: "w0", 4: "w1", 5: "w1", 6: "w1", 7: "w1"}
    groups = agent_groups(assignment, agents_per_scene=1)
    assert [g.tolist() for g in groups] == [[0, 2, 4, 6], [1, 3, 5, 7]]
    # whole scenes (teams) stay together; one scene cannot be split
    assert [g.tolist() for g in agent_groups({0: "w0", 1: "w1"}, agents_per_scene=3)] == [[0, 1, 2], [3, 4, 5]]
    assert [g.tolist() for g in agent_groups({0: "w0"}, agents_per_scene=4)] == [[0, 1, 2, 3]]


@pytest.fixture(scope="module")
def model():
    env = make_counter(num_envs=4, max_episode_steps=5, pool=small_pool(workers=2))
    wrapped = VecNormalize(VecMonitor(env), norm_obs_keys=["step"])
    model = PipelinedPPO("MultiInputPolicy", wrapped, n_steps=12, batch_size=24, n_epochs=1, seed=3,
                         policy_kwargs=visfly_policy_kwargs("resnet-tiny"))
    model.learn(48)
    yield model
    env.close()


def test_rollout_rows_line_up_per_agent(model):
    """Each stored row's log-probability and value are the policy's for that row's observation and
    action: rows of the two groups were not mixed up."""
    buf = model.rollout_buffer
    assert model.num_timesteps == 48 and buf.full
    assert sorted(np.concatenate(model.groups).tolist()) == [0, 1, 2, 3] and len(model.groups) == 2
    assert model.env.venv.venv.groups_in_flight == 0
    # the stored rows came from the policy before the last update: collect again with the current one
    model.collect_rollouts(model.env, _NullCallback(model), buf, model.n_steps)
    obs = {k: torch.as_tensor(v.reshape(-1, *v.shape[2:])) for k, v in buf.observations.items()}
    actions = torch.as_tensor(buf.actions.reshape(-1, buf.actions.shape[-1]))
    with torch.no_grad():
        values, log_prob, _ = model.policy.evaluate_actions(obs, actions)
    np.testing.assert_allclose(log_prob.numpy(), buf.log_probs.reshape(-1), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(values.numpy().reshape(-1), buf.values.reshape(-1), rtol=1e-4, atol=1e-4)


def test_episode_starts_follow_the_counter(model):
    """The counter task's ``step`` entry counts the episode's steps: a row whose start flag is set
    shows a fresh episode, the next row of the same agent one step more, whatever group it is in."""
    buf = model.rollout_buffer
    norm = model.env
    steps = norm.unnormalize_obs({"step": buf.observations["step"]})["step"][..., 0]  # (T, N)
    counted = np.rint(steps).astype(int)
    for t in range(1, counted.shape[0]):
        fresh = buf.episode_starts[t].astype(bool)
        assert (counted[t][fresh] == 0).all()
        assert (counted[t][~fresh] == counted[t - 1][~fresh] + 1).all()


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


class _NullCallback:
    """The callback interface collect_rollouts calls, doing nothing."""

    def __init__(self, model):
        self.model = model

    def on_rollout_start(self):
        pass

    def update_locals(self, _locals):
        pass

    def on_step(self):
        return True

    def on_rollout_end(self):
        pass
