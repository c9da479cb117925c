"""The Dict-observation feature extractor: sizes, normalisation, SB3 integration, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from gymnasium import spaces

from visfly_dist.errors import ConfigError
from visfly_dist.training.extractors import ImageNormalizer, VisflyExtractor, visfly_cnn, visfly_policy_kwargs


def dict_space(**entries: spaces.Box) -> spaces.Dict:
    return spaces.Dict(entries)


DEPTH = spaces.Box(0.0, 20.0, (1, 64, 64), np.float32)
RGB = spaces.Box(0, 255, (3, 48, 48), np.uint8)
STATE = spaces.Box(-np.inf, np.inf, (13,), np.float32)
TARGET = spaces.Box(-np.inf, np.inf, (4,), np.float32)
TEAM = spaces.Box(-np.inf, np.inf, (2, 13), np.float32)


def batch(space: spaces.Dict, n: int = 3) -> dict[str, torch.Tensor]:
    space.seed(0)
    return {k: torch.as_tensor(np.stack([s.sample() for _ in range(n)])) for k, s in space.spaces.items()}


@pytest.mark.parametrize("backbone", ["visfly-cnn", "resnet-tiny"])
def test_features_dim_counts_every_entry(backbone: str) -> None:
    space = dict_space(state=STATE, depth=DEPTH, rgb=RGB, target=TARGET, team=TEAM)
    ext = VisflyExtractor(space, backbone=backbone)
    assert ext.features_dim == 64 + 128 + 128 + 64 + 2 * 64
    out = ext(batch(space))
    assert out.shape == (3, ext.features_dim) and torch.isfinite(out).all()


def test_visfly_cnn_flatten_size_is_analytic() -> None:
    # 64 -conv5-> 60 -pool-> 30 -conv3-> 28 -pool-> 14 -conv3-> 12 -pool-> 6; 18 channels
    assert visfly_cnn(1)(torch.zeros(1, 1, 64, 64)).shape == (1, 18 * 6 * 6)
    ext = VisflyExtractor(dict_space(depth=DEPTH))
    assert ext.encoders["depth"].head[0].in_features == 18 * 6 * 6


def test_depth_is_normalised_by_far_and_rgb_by_255() -> None:
    depth = ImageNormalizer(DEPTH)
    x = torch.tensor([0.0, 5.0, 20.0, 35.0]).reshape(1, 1, 2, 2)
    assert torch.allclose(depth(x).flatten(), torch.tensor([0.0, 0.25, 1.0, 1.0]))
    log = ImageNormalizer(DEPTH, depth_scale="log")
    assert math.isclose(float(log(torch.full((1, 1, 1, 1), 5.0))), math.log1p(5.0) / math.log1p(20.0), rel_tol=1e-6)
    rgb = ImageNormalizer(RGB)
    pixel = torch.tensor([0, 51, 255], dtype=torch.uint8).reshape(1, 3, 1, 1)
    assert torch.allclose(rgb(pixel).flatten(), torch.tensor([0.0, 0.2, 1.0]))


def test_policy_kwargs_build_an_sb3_policy_that_acts() -> None:
    from stable_baselines3.common.policies import MultiInputActorCriticPolicy

    space = dict_space(state=STATE, depth=DEPTH, target=TARGET)
    policy = MultiInputActorCriticPolicy(space, spaces.Box(-1, 1, (4,), np.float32), lambda _: 3e-4, **visfly_policy_kwargs())
    assert isinstance(policy.features_extractor, VisflyExtractor)
    assert [m.out_features for m in policy.mlp_extractor.policy_net if isinstance(m, torch.nn.Linear)] == [64, 64]
    assert [m.out_features for m in policy.mlp_extractor.value_net if isinstance(m, torch.nn.Linear)] == [64, 64]
    space.seed(1)
    obs = {k: np.stack([s.sample() for _ in range(5)]) for k, s in space.spaces.items()}
    actions, _ = policy.predict(obs, deterministic=True)
    assert actions.shape == (5, 4) and np.all(np.abs(actions) <= 1)


@pytest.mark.parametrize("algorithm", ["SAC", "TD3", "DDPG"])
def test_policy_kwargs_build_an_off_policy_actor_and_critic(algorithm: str) -> None:
    """Off-policy critics read ``qf`` (SB3 asserts it): the same kwargs serve SAC, TD3 and DDPG."""
    import stable_baselines3
    from stable_baselines3.common.env_util import DummyVecEnv

    space = dict_space(state=STATE, depth=spaces.Box(0.0, 20.0, (1, 32, 32), np.float32))

    class SpacesOnly(DummyVecEnv):
        def __init__(self) -> None:  # the algorithm reads the spaces only until it learns
            self.num_envs, self.observation_space = 1, space
            self.action_space = spaces.Box(-1, 1, (4,), np.float32)

    model = getattr(stable_baselines3, algorithm)("MultiInputPolicy", SpacesOnly(), policy_kwargs=visfly_policy_kwargs(),
                                                  buffer_size=10, device="cpu")
    critic = model.policy.critic.q_networks[0]
    assert [m.out_features for m in critic if isinstance(m, torch.nn.Linear)] == [64, 64, 1]
    assert isinstance(model.policy.actor.features_extractor, VisflyExtractor)
    space.seed(2)
    actions, _ = model.predict({k: np.stack([s.sample() for _ in range(3)]) for k, s in space.spaces.items()},
                               deterministic=True)
    assert actions.shape == (3, 4) and np.all(np.abs(actions) <= 1)


def test_errors_name_the_bad_value() -> None:
    with pytest.raises(ConfigError, match="backbone='vgg'.*accepted"):
        VisflyExtractor(dict_space(depth=DEPTH), backbone="vgg")
    with pytest.raises(ConfigError, match="'depth' of shape \\(1, 8, 8\\) is too small"):
        VisflyExtractor(dict_space(depth=spaces.Box(0.0, 20.0, (1, 8, 8), np.float32)))
    assert VisflyExtractor(dict_space(depth=spaces.Box(0.0, 20.0, (1, 8, 8), np.float32)), backbone="resnet-tiny").features_dim == 128
    with pytest.raises(ConfigError, match="'mode'.*Box entries"):
        VisflyExtractor(spaces.Dict({"mode": spaces.Discrete(3)}))


@pytest.mark.parametrize("task", ["hover", "navigation", "landing", "gap_crossing", "racing"])
def test_forward_on_real_task_observations(task: str) -> None:
    from visfly_dist.tasks import make_env
    from visfly_dist.training.config import TrainConfig
    from visfly_dist.training.ppo import env_kwargs

    num_envs = 3 if task == "gap_crossing" else 2
    with make_env(task, num_envs=num_envs, **env_kwargs(TrainConfig(task=task, workers=1))) as env:
        obs = env.reset()
        obs, *_ = env.step(np.zeros((num_envs, 4), np.float32))
    space = env.observation_space
    ext = VisflyExtractor(space)
    expected = 0
    for key, sub in space.spaces.items():
        expected += 128 if len(sub.shape) == 3 else 64 * (sub.shape[0] if len(sub.shape) == 2 else 1)
    assert ext.features_dim == expected
    out = ext({k: torch.as_tensor(v) for k, v in obs.items()})
    assert out.shape == (num_envs, expected) and torch.isfinite(out).all()
