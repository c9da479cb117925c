"""OverlappedPPO: the next rollout collected during the update, and the decoupled-PPO lag correction."""

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.env_util import make_vec_env

from visfly_dist.training.overlap import IMPORTANCE_CLIP, OverlappedPPO, decouple_lagged_rollout


def pendulum_model(cls=PPO, **kwargs):
    env = make_vec_env("Pendulum-v1", n_envs=2, seed=0)
    return cls("MlpPolicy", env, n_steps=16, batch_size=16, n_epochs=1, seed=0, device="cpu", **kwargs)


def collected(model):
    model._setup_learn(10_000, None)
    callback = CallbackList([])
    callback.init_callback(model)
    assert model.collect_rollouts(model.env, callback, model.rollout_buffer, n_rollout_steps=model.n_steps)
    return model.rollout_buffer


def log_probs_of(policy, buffer):
    obs = torch.as_tensor(buffer.observations.reshape(-1, *buffer.observations.shape[2:]))
    actions = torch.as_tensor(buffer.actions.reshape(-1, *buffer.actions.shape[2:]))
    with torch.no_grad():
        return policy.get_distribution(obs).log_prob(actions).numpy().reshape(buffer.log_probs.shape)


def test_decoupling_a_rollout_of_the_current_policy_changes_nothing():
    model = pendulum_model()
    buffer = collected(model)
    advantages, log_probs = buffer.advantages.copy(), buffer.log_probs.copy()
    weights = decouple_lagged_rollout(model.policy, buffer)
    assert weights.shape == (16, 2)
    np.testing.assert_allclose(weights, 1.0, atol=1e-5)
    np.testing.assert_allclose(buffer.advantages, advantages, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(buffer.log_probs, log_probs, atol=1e-5)


def test_decoupling_weights_each_sample_by_proximal_over_behaviour_probability():
    model = pendulum_model()
    buffer = collected(model)
    behaviour, advantages = buffer.log_probs.copy(), buffer.advantages.copy()
    with torch.no_grad():  # the policy moves on (as one update would): mean and spread change
        model.policy.log_std.add_(0.4)
        model.policy.action_net.bias.add_(0.3)
    proximal = log_probs_of(model.policy, buffer)
    weights = decouple_lagged_rollout(model.policy, buffer)
    expected = np.minimum(np.exp(proximal - behaviour), IMPORTANCE_CLIP)
    assert np.ptp(expected) > 0.1  # the change is visible in the weights
    np.testing.assert_allclose(weights, expected, rtol=1e-4)
    np.testing.assert_allclose(buffer.log_probs, proximal, atol=1e-5)
    np.testing.assert_allclose(buffer.advantages, advantages * expected, rtol=1e-4, atol=1e-6)


class StepCounter(BaseCallback):
    def __init__(self):
        super().__init__()
        self.steps = 0

    def _on_step(self) -> bool:
        assert len(self.locals["infos"]) == 2
        self.steps += 1
        return True


class RecordingOverlappedPPO(OverlappedPPO):
    """Notes, per update, whether its rollout was lagged and the importance weights it logged."""

    def train(self) -> None:
        lagged = self._lagged
        super().train()
        self.updates.append((lagged, self.logger.name_to_value.get("train/importance_weight_mean")))


def test_overlapped_ppo_replays_every_step_and_corrects_every_lagged_update():
    model = pendulum_model(RecordingOverlappedPPO)
    model.updates = []
    counter = StepCounter()
    model.learn(total_timesteps=160, callback=counter)
    assert model.num_timesteps == 160 and counter.steps == 80  # every step replayed to the callbacks
    assert model._worker is None  # no collection left running
    # 5 rollouts: the first collected in the foreground, the next four during updates 1-4
    assert [lagged for lagged, _ in model.updates] == [False, True, True, True, True]
    weights = [w for lagged, w in model.updates if lagged]
    assert all(w is not None and 0.5 < w < IMPORTANCE_CLIP for w in weights)
    assert any(abs(w - 1.0) > 1e-4 for w in weights)  # the policy moved between behaviour and update
