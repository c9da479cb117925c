"""PPO's update with minibatches split across threads equals SB3's own update."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.logger import Logger

from visfly_dist.errors import ConfigError
from visfly_dist.training.extractors import visfly_policy_kwargs
from visfly_dist.training.parallel_update import shard_slices, sharded_ppo_train

N_ENVS, N_STEPS = 4, 32
IMAGE_SPACE = spaces.Dict({"depth": spaces.Box(0.0, 20.0, (1, 32, 32), np.float32),
                           "state": spaces.Box(-np.inf, np.inf, (7,), np.float32)})


class RecordingLogger(Logger):
    def __init__(self) -> None:
        super().__init__(folder=None, output_formats=[])
        self.values: dict[str, float] = {}

    def record(self, key: str, value: object, exclude: object = None) -> None:
        self.values[key] = value  # type: ignore[assignment]


def filled_model(obs_space: spaces.Space, action_space: spaces.Space, seed: int = 0, **kwargs: object) -> PPO:
    """A PPO model (no env) whose rollout buffer holds random observations and rewards."""
    torch.manual_seed(seed)
    policy_kwargs = visfly_policy_kwargs() if isinstance(obs_space, spaces.Dict) else {}
    model = PPO("MultiInputPolicy" if isinstance(obs_space, spaces.Dict) else "MlpPolicy", None, n_steps=N_STEPS,
                batch_size=40, n_epochs=3, policy_kwargs=policy_kwargs, seed=seed, device="cpu", verbose=0,
                _init_setup_model=False, **kwargs)
    model.observation_space, model.action_space, model.n_envs = obs_space, action_space, N_ENVS
    model._setup_model()
    model.set_logger(RecordingLogger())
    rng = np.random.default_rng(seed)
    for _ in range(N_STEPS):
        if isinstance(obs_space, spaces.Dict):
            obs = {k: rng.uniform(0, 20, (N_ENVS, *s.shape)).astype(np.float32) for k, s in obs_space.spaces.items()}
            tensor = {k: torch.as_tensor(v) for k, v in obs.items()}
        else:
            obs = rng.normal(size=(N_ENVS, *obs_space.shape)).astype(np.float32)
            tensor = torch.as_tensor(obs)
        with torch.no_grad():
            actions, values, log_probs = model.policy(tensor)
        model.rollout_buffer.add(obs, actions.numpy(), rng.normal(size=N_ENVS).astype(np.float32),
                                 np.zeros(N_ENVS, dtype=bool), values, log_probs)
    model.rollout_buffer.compute_returns_and_advantage(last_values=torch.zeros(N_ENVS), dones=np.zeros(N_ENVS, dtype=bool))
    return model


def sb3_update(model: PPO) -> None:
    np.random.seed(7)  # the rollout buffer's minibatch permutation
    model.train()


def sharded_update(model: PPO, shards: int) -> None:
    np.random.seed(7)
    sharded_ppo_train(model, shards)


def max_parameter_difference(a: PPO, b: PPO) -> float:
    return max(float((p - q).detach().abs().max()) for p, q in zip(a.policy.parameters(), b.policy.parameters()))


@pytest.mark.parametrize("shards", [1, 2, 3])
def test_split_minibatches_give_sb3s_update_and_logs(shards: int) -> None:
    torch.set_num_threads(1)
    box = spaces.Box(-1.0, 1.0, (4,), np.float32)
    reference, split = filled_model(IMAGE_SPACE, box), filled_model(IMAGE_SPACE, box)
    assert max_parameter_difference(reference, split) == 0.0
    before = [p.detach().clone() for p in split.policy.parameters()]
    for _ in range(2):  # the second update starts from a moved policy: ratios and clipping are not trivial
        sb3_update(reference)
        sharded_update(split, shards)
    moved = max(float((p.detach() - q).abs().max()) for p, q in zip(split.policy.parameters(), before))
    assert moved > 1e-3
    assert max_parameter_difference(reference, split) < 2e-5 * max(moved, 1.0)
    ours, theirs = split.logger.values, reference.logger.values  # type: ignore[attr-defined]
    assert set(ours) == set(theirs)
    for key in ("train/entropy_loss", "train/policy_gradient_loss", "train/value_loss", "train/approx_kl",
                "train/clip_fraction", "train/loss", "train/std", "train/explained_variance"):
        assert ours[key] == pytest.approx(theirs[key], rel=1e-4, abs=1e-6), key
    assert ours["train/n_updates"] == theirs["train/n_updates"] == 6
    assert theirs["train/clip_fraction"] > 0  # the comparison covered clipped samples


def test_discrete_actions_and_value_clipping_follow_sb3_too() -> None:
    vector = spaces.Box(-np.inf, np.inf, (6,), np.float32)
    reference = filled_model(vector, spaces.Discrete(5), clip_range_vf=0.1, ent_coef=0.01)
    split = filled_model(vector, spaces.Discrete(5), clip_range_vf=0.1, ent_coef=0.01)
    for _ in range(2):
        sb3_update(reference)
        sharded_update(split, 4)
    assert max_parameter_difference(reference, split) < 1e-5
    assert split.logger.values["train/value_loss"] == pytest.approx(reference.logger.values["train/value_loss"], rel=1e-4)  # type: ignore[attr-defined]


def test_shard_slices_cover_the_batch_without_empty_parts() -> None:
    for size, shards in [(512, 2), (7, 3), (2, 5), (1, 1), (10, 10)]:
        parts = shard_slices(size, shards)
        assert [i for s in parts for i in range(size)[s]] == list(range(size))
        assert len(parts) == min(size, shards) and all(s.stop > s.start for s in parts)
    with pytest.raises(ConfigError):
        shard_slices(8, 0)
