"""Initial-state randomisation: per-component uniform or normal distributions, explicitly seeded."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import torch

from visfly_dist.dynamics.rotations import quat_from_euler, quat_from_rotvec
from visfly_dist.errors import ConfigError

KINDS = ("uniform", "normal")
ORIENTATION_MODES = ("euler", "small_angle")


@dataclass(frozen=True)
class Distribution:
    """A distribution over 3-vectors, independent per axis.

    Attributes:
        kind: ``"uniform"`` (``a`` centre, ``b`` half-width: values in ``[a - b, a + b]``) or
            ``"normal"`` (``a`` mean, ``b`` standard deviation).
        a: centre or mean per axis.
        b: half-width or standard deviation per axis, >= 0 (zero gives ``a`` exactly).
    """

    kind: str = "uniform"
    a: Sequence[float] = (0.0, 0.0, 0.0)
    b: Sequence[float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        problems = []
        if self.kind not in KINDS:
            problems.append(f"unknown kind={self.kind!r}: use one of {list(KINDS)}")
        if len(tuple(self.a)) != 3 or len(tuple(self.b)) != 3:
            problems.append(f"a={self.a!r} and b={self.b!r} must have 3 entries each")
        elif any(x < 0 for x in self.b):
            problems.append(f"b={self.b!r} (half-width or std) must be >= 0")
        if problems:
            raise ConfigError("invalid Distribution: " + "; ".join(problems))

    def sample(self, n: int, generator: torch.Generator, dtype: torch.dtype = torch.float32,
               device: torch.device | str = "cpu") -> torch.Tensor:
        """(n, 3) samples; drawn on ``generator``'s device, then moved to ``device``."""
        a = torch.tensor(self.a, dtype=torch.float64)
        b = torch.tensor(self.b, dtype=torch.float64)
        gen_device = generator.device
        if self.kind == "uniform":
            unit = torch.rand(n, 3, generator=generator, dtype=torch.float64, device=gen_device) * 2 - 1
        else:
            unit = torch.randn(n, 3, generator=generator, dtype=torch.float64, device=gen_device)
        return (a + b * unit.cpu()).to(dtype=dtype, device=device)


@dataclass(frozen=True)
class InitialSample:
    """Sampled initial components of n agents; pass them to ``Quadrotor.initial_state``.

    Attributes:
        pos: (n, 3) m, offsets to add to each agent's spawn point.
        vel: (n, 3) m/s, world frame.
        quat: (n, 4) unit ``wxyz``.
        omega: (n, 3) rad/s, body rates.
    """

    pos: torch.Tensor
    vel: torch.Tensor
    quat: torch.Tensor
    omega: torch.Tensor


@dataclass(frozen=True)
class InitialStateSampler:
    """Random initial states, one distribution per component.

    Attributes:
        pos: position offsets, m.
        vel: velocity, m/s.
        orientation: ``(roll, pitch, yaw)`` radians with ``orientation_mode="euler"``, or a rotation
            vector (axis times angle, radians) with ``"small_angle"``.
        omega: body rates, rad/s.
        orientation_mode: ``"euler"`` or ``"small_angle"``.

    Example:
        sampler = InitialStateSampler(vel=Distribution("normal", b=(0.5, 0.5, 0.2)))
        s = sampler.sample(n, torch.Generator().manual_seed(0))
        state = quad.initial_state(pos=spawn + s.pos, vel=s.vel, quat=s.quat, omega=s.omega)
    """

    pos: Distribution = field(default_factory=Distribution)
    vel: Distribution = field(default_factory=Distribution)
    orientation: Distribution = field(default_factory=Distribution)
    omega: Distribution = field(default_factory=Distribution)
    orientation_mode: str = "euler"

    def __post_init__(self) -> None:
        if self.orientation_mode not in ORIENTATION_MODES:
            raise ConfigError(f"unknown orientation_mode={self.orientation_mode!r}: use one of "
                              f"{list(ORIENTATION_MODES)}")
        for name in ("pos", "vel", "orientation", "omega"):
            if not isinstance(getattr(self, name), Distribution):
                raise ConfigError(f"{name} must be a Distribution, got {type(getattr(self, name)).__name__}")

    def sample(self, n: int, generator: torch.Generator, dtype: torch.dtype = torch.float32,
               device: torch.device | str = "cpu") -> InitialSample:
        """Draw ``n`` initial states; the same generator state gives the same sample."""
        pos = self.pos.sample(n, generator, dtype, device)
        vel = self.vel.sample(n, generator, dtype, device)
        angles = self.orientation.sample(n, generator, torch.float64, device)
        quat = quat_from_euler(angles) if self.orientation_mode == "euler" else quat_from_rotvec(angles)
        omega = self.omega.sample(n, generator, dtype, device)
        return InitialSample(pos=pos, vel=vel, quat=quat.to(dtype), omega=omega)
