"""Image backbones (``--backbone``): feature shapes, training on a tiny batch, PPO and ONNX use, the bench."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gymnasium import spaces

from visfly_dist.bench.update import bench_backbone
from visfly_dist.training.config import BACKBONES, TrainConfig
from visfly_dist.training.extractors import IMAGE_FEATURES, ImageEncoder, VisflyExtractor, visfly_policy_kwargs

IMAGES = {"depth": spaces.Box(0.0, 20.0, (1, 64, 64), np.float32), "rgb": spaces.Box(0, 255, (3, 64, 64), np.uint8)}


def images(space: spaces.Box, n: int, seed: int) -> torch.Tensor:
    """``n`` images with some structure: 8x8 blocks of random levels around a per-image level."""
    rng = np.random.default_rng(seed)
    high = 255.0 if space.dtype == np.uint8 else 25.0  # depth beyond far too: the normaliser clips it
    c, h, w = space.shape
    blocks = rng.uniform(0.0, 1.0, (n, 1, 1, 1)) * 0.7 + rng.uniform(0.0, 0.3, (n, c, h // 8, w // 8))
    return torch.as_tensor((blocks.repeat(8, axis=2).repeat(8, axis=3) * high).astype(space.dtype))


def test_the_new_backbones_are_offered() -> None:
    assert {"mobilenet-tiny", "efficientnet-tiny"} <= set(BACKBONES)
    for backbone in BACKBONES:
        assert not [p for p in TrainConfig(task="navigation", backbone=backbone).resolved().problems() if "backbone" in p]


@pytest.mark.parametrize("image", list(IMAGES))
@pytest.mark.parametrize("backbone", BACKBONES)
def test_feature_shape(backbone: str, image: str) -> None:
    space = spaces.Dict({image: IMAGES[image], "state": spaces.Box(-np.inf, np.inf, (13,), np.float32)})
    extractor = VisflyExtractor(space, backbone=backbone)
    features = extractor({image: images(IMAGES[image], 5, 0), "state": torch.zeros(5, 13)})
    assert features.shape == (5, extractor.features_dim) == (5, IMAGE_FEATURES + 64)
    assert torch.isfinite(features).all()


@pytest.mark.parametrize("image", list(IMAGES))
@pytest.mark.parametrize("backbone", BACKBONES)
def test_backbone_trains_on_a_tiny_batch(backbone: str, image: str) -> None:
    """Regressing 4 random targets from 4 images with Adam: after 25 steps the loss is under 3/4 of its
    start (the new backbones reach under 1/10; resnet-tiny on depth about 0.6)."""
    torch.manual_seed(0)
    encoder = ImageEncoder(IMAGES[image], backbone, "linear", image)
    head = torch.nn.Linear(IMAGE_FEATURES, 4)
    x = images(IMAGES[image], 4, 1)
    y = torch.as_tensor(np.random.default_rng(2).normal(size=(4, 4)).astype(np.float32))
    params = [*encoder.parameters(), *head.parameters()]
    optimizer = torch.optim.Adam(params, lr=3e-3)
    losses = []
    for _ in range(25):
        optimizer.zero_grad()
        loss = torch.nn.functional.mse_loss(head(encoder(x)), y)
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in encoder.trunk.parameters())
    assert losses[-1] < 0.75 * losses[0], (losses[0], losses[-1])
    if backbone in ("mobilenet-tiny", "efficientnet-tiny"):
        assert losses[-1] < 0.1 * losses[0], (losses[0], losses[-1])


@pytest.mark.parametrize("backbone", BACKBONES)
def test_policy_acts_alike_in_rollout_and_update_modes(backbone: str) -> None:
    """PPO evaluates rollouts in eval mode and updates in train mode: the same function is needed
    (no batch statistics), else its probability ratio starts away from 1."""
    from stable_baselines3 import PPO

    space = spaces.Dict({"depth": IMAGES["depth"], "state": spaces.Box(-np.inf, np.inf, (13,), np.float32)})
    model = PPO("MultiInputPolicy", None, policy_kwargs=visfly_policy_kwargs(backbone), device="cpu", seed=0,
                _init_setup_model=False)
    model.observation_space, model.action_space, model.n_envs = space, spaces.Box(-1, 1, (4,), np.float32), 1
    model._setup_model()
    obs = {"depth": images(IMAGES["depth"], 6, 3), "state": torch.randn(6, 13)}
    actions = torch.zeros(6, 4)
    with torch.no_grad():
        model.policy.set_training_mode(False)
        values_eval, logp_eval, _ = model.policy.evaluate_actions(obs, actions)
        model.policy.set_training_mode(True)
        values_train, logp_train, _ = model.policy.evaluate_actions(obs, actions)
        _, logp_half, _ = model.policy.evaluate_actions({k: v[:3] for k, v in obs.items()}, actions[:3])
    torch.testing.assert_close(logp_train, logp_eval)
    torch.testing.assert_close(values_train, values_eval)
    torch.testing.assert_close(logp_half, logp_eval[:3], rtol=1e-5, atol=1e-5)  # a shard of a minibatch too


@pytest.mark.parametrize("backbone", ["mobilenet-tiny", "efficientnet-tiny"])
def test_new_backbones_export_to_onnx(backbone: str, tmp_path) -> None:
    onnxruntime = pytest.importorskip("onnxruntime")
    from stable_baselines3 import PPO

    from visfly_dist.training.export import export_policy

    space = spaces.Dict({"depth": IMAGES["depth"], "state": spaces.Box(-np.inf, np.inf, (13,), np.float32)})
    model = PPO("MultiInputPolicy", None, policy_kwargs=visfly_policy_kwargs(backbone), device="cpu", seed=0,
                _init_setup_model=False)
    model.observation_space, model.action_space, model.n_envs = space, spaces.Box(-1, 1, (4,), np.float32), 1
    model._setup_model()
    with torch.no_grad():
        model.policy.action_net.weight.normal_(0.0, 1.0, generator=torch.Generator().manual_seed(0))
    export_policy(model.policy, tmp_path / "p.onnx")
    obs = {"depth": images(IMAGES["depth"], 7, 4).numpy(), "state": np.random.default_rng(5).normal(size=(7, 13)).astype(np.float32)}
    expected, _ = model.predict(obs, deterministic=True)
    got = onnxruntime.InferenceSession(str(tmp_path / "p.onnx")).run(["action"], obs)[0]
    # float32 rounding of onnxruntime's group norms and depthwise convolutions against torch's, through
    # an action layer with weights of std 1 (a trained one's are far smaller): within 1e-4
    np.testing.assert_allclose(got, expected, atol=1e-4, rtol=0)


def test_bench_gives_a_cost_per_image_for_each_backbone() -> None:
    rows = [bench_backbone(b, "depth", batch=4, reps=1) for b in BACKBONES]
    assert [r["backbone"] for r in rows] == list(BACKBONES)
    for row in rows:
        assert row["params"] > 10_000 and row["fwd_bwd_ms_per_image"] > 0 and row["forward_ms_per_image"] > 0
