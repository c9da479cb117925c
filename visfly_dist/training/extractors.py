"""Feature extractors and policy settings for Dict observations, after VisFly's policy.

Every entry of the observation dict gets its own small network; their outputs are concatenated:

| entry shape        | what it is                          | network                                  |
|--------------------|-------------------------------------|------------------------------------------|
| ``(C, H, W)``      | a camera image (depth, RGB, ...)    | image backbone -> 128, ReLU              |
| ``(D,)``           | a vector (``state``, ``target``...) | MLP 128-64, ReLU                         |
| ``(K, D)``         | a set of rows (e.g. teammates)      | one MLP 128-64 shared by the rows, concat|

Images are normalised inside the network, so SB3 must not touch them (``normalize_images=False``,
which :func:`visfly_policy_kwargs` sets):

- depth (float, 1 channel): metres divided by the space's upper bound (``far``, 20 m by default),
  clipped to ``[0, 1]``; with ``depth_scale="log"``, ``log1p(d) / log1p(far)`` instead, which gives
  near obstacles more of the range;
- uint8 (RGB): divided by 255;
- segmentation (uint16 ids): divided by the space's upper bound.

Image backbones: ``"visfly-cnn"`` (VisFly's: conv 6/12/18 channels, kernels 5/3/3, each followed by
a 2x2 max-pool and ReLU, then a linear layer to 128), ``"resnet-tiny"`` (three residual stages of
16/32/64 channels with stride-2 downsampling, global average pooling, linear to 128),
``"mobilenet-tiny"`` (MobileNetV2's inverted residuals: depthwise 3x3 between 1x1 expansion and
projection) and ``"efficientnet-tiny"`` (EfficientNet's MBConv blocks with squeeze-excitation and
SiLU); both of the last two end in a 1x1 convolution to 128 channels and global average pooling,
take any image size, and normalise with GroupNorm (per sample) rather than BatchNorm, whose batch
statistics differ between SB3's rollouts (eval mode) and updates (train mode, minibatches split
across threads). Their blocks follow torchvision's (``Conv2dNormActivation``, ``InvertedResidual``,
``SqueezeExcitation``, ``MBConv``) but are written here: the torchvision 0.28 wheel that matches
torch 2.13 is built for CUDA and does not import against the CPU build of torch this project pins.

Training with your own algorithm on a visfly-dist env::

    from stable_baselines3 import PPO
    from visfly_dist import make_env
    from visfly_dist.training.extractors import visfly_policy_kwargs

    env = make_env("navigation", num_envs=100)
    model = PPO("MultiInputPolicy", env, policy_kwargs=visfly_policy_kwargs())
    model.learn(1_000_000)

Any SB3 algorithm with a ``MultiInputPolicy`` (SAC, TD3, A2C, RecurrentPPO from sb3-contrib) takes
the same ``policy_kwargs``; for your own torch code, ``VisflyExtractor(env.observation_space)``
maps a dict of batched tensors to ``(B, features_dim)`` features.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from visfly_dist.errors import ConfigError
from visfly_dist.training.config import BACKBONES
from visfly_dist.training.conv_pool import conv_maxpool2

DEPTH_SCALES = ("linear", "log")
IMAGE_FEATURES = 128
VECTOR_HIDDEN = (128, 64)
DEFAULT_FAR = 20.0


class ImageNormalizer(nn.Module):
    """Maps raw image observations to roughly ``[0, 1]`` floats (see the module docstring)."""

    def __init__(self, space: spaces.Box, depth_scale: str = "linear") -> None:
        super().__init__()
        high = float(np.max(space.high)) if np.all(np.isfinite(space.high)) else DEFAULT_FAR
        self.kind = "uint8" if space.dtype == np.uint8 else ("depth" if np.issubdtype(space.dtype, np.floating) else "ids")
        self.log = self.kind == "depth" and depth_scale == "log"
        self.scale = 255.0 if self.kind == "uint8" else max(high, 1e-6)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x.float()
        if self.kind != "depth":
            x = x / self.scale
        elif self.log:
            x = torch.log1p(x.clamp(0.0, self.scale)) / math.log1p(self.scale)
        else:
            x = x.clamp(0.0, self.scale) / self.scale
        # channels-last (NHWC) memory makes the small convolutions about 1.5x faster on CPU
        return x.contiguous(memory_format=torch.channels_last)


class ConvPoolSequential(nn.Sequential):
    """An ``nn.Sequential`` that runs each ``Conv2d`` directly followed by ``MaxPool2d(2)`` as one
    fused step (:func:`~visfly_dist.training.conv_pool.conv_maxpool2`): the same function and the
    same parameter names as the plain sequence, so checkpoints load either way.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if torch.onnx.is_in_onnx_export():
            return super().forward(x)  # ONNX export (visfly-dist export): the plain layers, no native kernel
        layers = list(self)
        i = 0
        while i < len(layers):
            layer = layers[i]
            following = layers[i + 1] if i + 1 < len(layers) else None
            if isinstance(layer, nn.Conv2d) and _is_pool2(following):
                x = conv_maxpool2(x, layer)
                i += 2
            else:
                x = layer(x)
                i += 1
        return x


def _is_pool2(layer: nn.Module | None) -> bool:
    """Whether ``layer`` is a plain 2x2, stride-2, unpadded max-pool."""
    return (isinstance(layer, nn.MaxPool2d) and layer.kernel_size in (2, (2, 2)) and layer.stride in (2, (2, 2))
            and layer.padding in (0, (0, 0)) and layer.dilation in (1, (1, 1)) and not layer.ceil_mode
            and not layer.return_indices)


def visfly_cnn(in_channels: int) -> nn.Sequential:
    """VisFly's image trunk (without the final linear layer): 6/12/18 channels, kernels 5/3/3.

    Each convolution is followed by a 2x2 max-pool and a ReLU: the same function as ReLU then pool
    (both are monotone, so they commute), with the ReLU on a quarter of the values. Convolution and
    pool run fused (:class:`ConvPoolSequential`); on the first layer that made the extractor's
    forward and backward pass about 1.2x faster on CPU, and its inference about 1.4x.
    """
    layers: list[nn.Module] = []
    for out_channels, kernel in zip((6, 12, 18), (5, 3, 3)):
        layers += [nn.Conv2d(in_channels, out_channels, kernel), nn.MaxPool2d(2), nn.ReLU()]
        in_channels = out_channels
    return ConvPoolSequential(*layers, nn.Flatten())


class ResidualBlock(nn.Module):
    """Two 3x3 convolutions with a skip connection; ``stride`` 2 halves the resolution."""

    def __init__(self, in_channels: int, out_channels: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, padding=1)
        self.skip = (
            nn.Identity()
            if stride == 1 and in_channels == out_channels
            else nn.Conv2d(in_channels, out_channels, 1, stride=stride)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(self.conv2(torch.relu(self.conv1(x))) + self.skip(x))


def resnet_tiny(in_channels: int) -> nn.Sequential:
    """A small residual CNN: stem 16, stages 16/32/64 (the last two stride 2), global average pool."""
    return nn.Sequential(
        nn.Conv2d(in_channels, 16, 3, padding=1),
        nn.ReLU(),
        ResidualBlock(16, 16, 1),
        ResidualBlock(16, 32, 2),
        ResidualBlock(32, 64, 2),
        nn.AdaptiveAvgPool2d(1),
        nn.Flatten(),
    )


def _norm(channels: int) -> nn.GroupNorm:
    """Group normalisation with up to 8 groups: per sample, so rollouts (eval mode) and PPO updates
    (train mode, minibatches split across threads) compute the same function, which BatchNorm's
    batch statistics would not (PPO's probability ratio would start away from 1)."""
    return nn.GroupNorm(math.gcd(channels, 8), channels)


class ConvNormAct(nn.Sequential):
    """Convolution (no bias), group norm, activation: torchvision's ``Conv2dNormActivation`` with
    :func:`_norm` in place of BatchNorm; ``groups=channels`` makes it depthwise."""

    def __init__(self, in_channels: int, out_channels: int, kernel: int = 3, stride: int = 1, groups: int = 1,
                 activation: type[nn.Module] | None = nn.ReLU6) -> None:
        layers: list[nn.Module] = [nn.Conv2d(in_channels, out_channels, kernel, stride, (kernel - 1) // 2, groups=groups, bias=False),
                                   _norm(out_channels)]
        if activation is not None:
            layers.append(activation())
        super().__init__(*layers)


class InvertedResidual(nn.Module):
    """MobileNetV2's block (Sandler et al. 2018; torchvision's ``InvertedResidual``): 1x1 expansion
    by ``expand``, 3x3 depthwise convolution (``stride``), linear 1x1 projection; a skip connection
    when the shape is kept."""

    def __init__(self, in_channels: int, out_channels: int, stride: int, expand: int) -> None:
        super().__init__()
        hidden = in_channels * expand
        layers: list[nn.Module] = [] if expand == 1 else [ConvNormAct(in_channels, hidden, 1)]
        layers += [ConvNormAct(hidden, hidden, 3, stride, groups=hidden), ConvNormAct(hidden, out_channels, 1, activation=None)]
        self.block = nn.Sequential(*layers)
        self.residual = stride == 1 and in_channels == out_channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.block(x) if self.residual else self.block(x)


class SqueezeExcitation(nn.Module):
    """Channel attention (Hu et al. 2018; torchvision's ``SqueezeExcitation``): global average,
    1x1 down to ``squeeze`` channels, SiLU, 1x1 back, sigmoid, scales the input's channels."""

    def __init__(self, channels: int, squeeze: int) -> None:
        super().__init__()
        self.fc1 = nn.Conv2d(channels, squeeze, 1)
        self.fc2 = nn.Conv2d(squeeze, channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        scale = torch.sigmoid(self.fc2(torch.nn.functional.silu(self.fc1(x.mean(dim=(2, 3), keepdim=True)))))
        return x * scale


class MBConv(nn.Module):
    """EfficientNet's block (Tan and Le 2019; torchvision's ``MBConv`` without stochastic depth):
    1x1 expansion, ``kernel`` depthwise convolution, squeeze-excitation (a quarter of the input
    channels), linear 1x1 projection, SiLU activations; a skip connection when the shape is kept."""

    def __init__(self, in_channels: int, out_channels: int, kernel: int, stride: int, expand: int) -> None:
        super().__init__()
        hidden = in_channels * expand
        layers: list[nn.Module] = [] if expand == 1 else [ConvNormAct(in_channels, hidden, 1, activation=nn.SiLU)]
        layers += [ConvNormAct(hidden, hidden, kernel, stride, groups=hidden, activation=nn.SiLU),
                   SqueezeExcitation(hidden, max(1, in_channels // 4)),
                   ConvNormAct(hidden, out_channels, 1, activation=None)]
        self.block = nn.Sequential(*layers)
        self.residual = stride == 1 and in_channels == out_channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.block(x) if self.residual else self.block(x)


def mobilenet_tiny(in_channels: int) -> nn.Sequential:
    """A MobileNetV2-style trunk for small images: stem 3x3/2 to 16, inverted residuals 16, 24/2, 24,
    32/2, 32, 64/2 (expansion 4 but the first), 1x1 to 128, global average pool (64x64 -> 4x4 -> 128)."""
    return nn.Sequential(
        ConvNormAct(in_channels, 16, 3, 2),
        InvertedResidual(16, 16, 1, 1),
        InvertedResidual(16, 24, 2, 4),
        InvertedResidual(24, 24, 1, 4),
        InvertedResidual(24, 32, 2, 4),
        InvertedResidual(32, 32, 1, 4),
        InvertedResidual(32, 64, 2, 4),
        ConvNormAct(64, 128, 1),
        nn.AdaptiveAvgPool2d(1),
        nn.Flatten(),
    )


def efficientnet_tiny(in_channels: int) -> nn.Sequential:
    """An EfficientNet-B0-style trunk for small images: stem 3x3/2 to 16, MBConv 16 (k3, expansion 1),
    24/2 (k3), 40/2 (k5), 64/2 (k3) with expansion 4, 1x1 to 128, global average pool; SiLU."""
    return nn.Sequential(
        ConvNormAct(in_channels, 16, 3, 2, activation=nn.SiLU),
        MBConv(16, 16, 3, 1, 1),
        MBConv(16, 24, 3, 2, 4),
        MBConv(24, 40, 5, 2, 4),
        MBConv(40, 64, 3, 2, 4),
        ConvNormAct(64, 128, 1, activation=nn.SiLU),
        nn.AdaptiveAvgPool2d(1),
        nn.Flatten(),
    )


TRUNKS = {"visfly-cnn": visfly_cnn, "resnet-tiny": resnet_tiny, "mobilenet-tiny": mobilenet_tiny,
          "efficientnet-tiny": efficientnet_tiny}
"""Backbone name (``config.BACKBONES``) -> trunk builder ``(in_channels) -> nn.Module`` giving ``(B, F)``."""


class ImageEncoder(nn.Module):
    """Normaliser, backbone and a linear layer to 128 features, sized with one dummy forward pass.

    The backbone runs in channels-last (NHWC) memory, which makes these small convolutions about
    1.5x faster on CPU. Its weights are switched at the first forward pass, not here, because SB3
    re-initialises them after construction and its orthogonal init needs contiguous weights.
    """

    def __init__(self, space: spaces.Box, backbone: str, depth_scale: str, key: str) -> None:
        super().__init__()
        self.normalizer = ImageNormalizer(space, depth_scale)
        self.trunk = TRUNKS[backbone](space.shape[0])
        with torch.no_grad():
            try:
                flat = self.trunk(self.normalizer(torch.zeros((1, *space.shape)))).shape[1]
            except RuntimeError as exc:
                raise ConfigError(
                    f"observation {key!r} of shape {space.shape} is too small for backbone {backbone!r} "
                    f"({exc}); use images of at least 32x32 or backbone='resnet-tiny'"
                ) from exc
        self.head = nn.Sequential(nn.Linear(flat, IMAGE_FEATURES), nn.ReLU())
        self._channels_last = False

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self._channels_last:
            self.trunk.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # not in torch's stubs
            self._channels_last = True
        return self.head(self.trunk(self.normalizer(x)))


def mlp(in_dim: int, hidden: tuple[int, ...] = VECTOR_HIDDEN) -> nn.Sequential:
    """Linear + ReLU layers of the given widths."""
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [nn.Linear(in_dim, width), nn.ReLU()]
        in_dim = width
    return nn.Sequential(*layers)


class RowwiseMLP(nn.Module):
    """One MLP applied to each row of a ``(B, K, D)`` input; the ``K`` outputs are concatenated."""

    def __init__(self, rows: int, dim: int) -> None:
        super().__init__()
        self.net = mlp(dim)
        self.out_dim = rows * VECTOR_HIDDEN[-1]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x.float()).flatten(1)


class VisflyExtractor(BaseFeaturesExtractor):
    """Per-entry encoders for a Dict observation space, concatenated (see the module docstring).

    Args:
        observation_space: a ``spaces.Dict`` of ``Box`` entries: images ``(C, H, W)``, vectors
            ``(D,)`` or row sets ``(K, D)``.
        backbone: image backbone, one of ``BACKBONES``.
        depth_scale: ``"linear"`` (metres / far) or ``"log"`` (``log1p(d) / log1p(far)``).

    Attributes:
        features_dim: width of the output, ``128`` per image + ``64`` per vector and per row.
    """

    def __init__(self, observation_space: spaces.Dict, backbone: str = "visfly-cnn", depth_scale: str = "linear") -> None:
        if not isinstance(observation_space, spaces.Dict):
            raise ConfigError(f"VisflyExtractor needs a spaces.Dict observation space, got {observation_space!r}")
        if backbone not in BACKBONES:
            raise ConfigError(f"backbone={backbone!r} is not known; accepted: {BACKBONES}")
        if depth_scale not in DEPTH_SCALES:
            raise ConfigError(f"depth_scale={depth_scale!r} is not known; accepted: {DEPTH_SCALES}")
        encoders: dict[str, nn.Module] = {}
        total = 0
        for key, space in observation_space.spaces.items():
            if not isinstance(space, spaces.Box) or len(space.shape) not in (1, 2, 3):
                raise ConfigError(
                    f"observation {key!r} is {space!r}; VisflyExtractor accepts Box entries of shape (D,), (K, D) or (C, H, W)"
                )
            if len(space.shape) == 3:
                encoders[key] = ImageEncoder(space, backbone, depth_scale, key)
                total += IMAGE_FEATURES
            elif len(space.shape) == 2:
                rowwise = RowwiseMLP(*space.shape)
                encoders[key] = rowwise
                total += rowwise.out_dim
            else:
                encoders[key] = mlp(space.shape[0])
                total += VECTOR_HIDDEN[-1]
        super().__init__(observation_space, features_dim=total)
        self.encoders = nn.ModuleDict(encoders)

    def forward(self, observations: dict[str, torch.Tensor]) -> torch.Tensor:
        return torch.cat([enc(observations[key].float()) for key, enc in self.encoders.items()], dim=1)


def visfly_policy_kwargs(backbone: str = "visfly-cnn", depth_scale: str = "linear") -> dict[str, Any]:
    """SB3 ``policy_kwargs`` for ``"MultiInputPolicy"``: VisflyExtractor, actor/critic 64-64 ReLU.

    ``net_arch`` names the critic twice, as on-policy (``vf``: PPO, A2C) and off-policy (``qf``:
    SAC, TD3, DDPG) algorithms call it; each reads its own key, so one dict serves them all.

    ``normalize_images=False`` because the extractor normalises images itself (float depth in
    metres would otherwise be treated as a flat vector or divided by 255).
    """
    if backbone not in BACKBONES:
        raise ConfigError(f"backbone={backbone!r} is not known; accepted: {BACKBONES}")
    return dict(
        features_extractor_class=VisflyExtractor,
        features_extractor_kwargs=dict(backbone=backbone, depth_scale=depth_scale),
        net_arch=dict(pi=[64, 64], vf=[64, 64], qf=[64, 64]),
        activation_fn=nn.ReLU,
        normalize_images=False,
    )
