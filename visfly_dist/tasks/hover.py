"""Hover: fly to a point and stay there (state-based, dense reward; quick to learn).

| observation | meaning                                                           | unit          | range    |
|-------------|-------------------------------------------------------------------|---------------|----------|
| ``state``   | position minus target (3), velocity (3), quaternion wxyz (4), body rates (3) | m, m/s, -, rad/s | unbounded |
| camera name | one entry per configured camera (none by default)                 | see camera    | see camera |

Action: ``Box(-1, 1, (4,))`` for the configured controller (CTBR by default).

Reward per step: ``1 - 0.5 d - 0.05 |v| - 0.02 |omega|`` with ``d`` the distance to the target (m),
and ``-fail_penalty`` on failure. Termination: failure only (collision, out of bounds, or
``d > max_distance``); there is no success state, so ``is_success`` stays false. Truncation: the
time limit (``max_episode_steps``, 100 steps of 0.03 s by default).
Spawn: uniform in ``target ± spawn_half_width``, 0.3 m clear of obstacles.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from visfly_dist.client.config import EnvConfig
from visfly_dist.client.env_base import DroneEnvBase, Spawn
from visfly_dist.tasks.common import vec3_problem


@dataclass
class HoverConfig(EnvConfig):
    """Hover settings (see the module docstring); EnvConfig fields keep their meaning.

    Attributes:
        target: the point to hold, world frame, m.
        spawn_half_width: spawn box half extents around the target, m.
        max_distance: the episode fails beyond this distance from the target, m.
        fail_penalty: reward subtracted on failure.
    """

    scenes: tuple[str, ...] = ("gen:empty",)
    max_episode_steps: int = 100
    target: tuple[float, float, float] = (1.0, 0.0, 1.5)
    spawn_half_width: tuple[float, float, float] = (0.5, 0.5, 0.5)
    max_distance: float = 2.0
    fail_penalty: float = 10.0

    def problems(self) -> list[str]:
        out = super().problems() + vec3_problem("target", self.target)
        out += vec3_problem("spawn_half_width", self.spawn_half_width, positive=True)
        if not isinstance(self.max_distance, (int, float)) or not self.max_distance > 0:
            out.append(f"max_distance={self.max_distance!r} must be a positive number of metres")
        return out


class HoverEnv(DroneEnvBase):
    """Hold a drone at ``config.target``."""

    config_class = HoverConfig
    config: HoverConfig

    def __init__(self, config: HoverConfig | None = None) -> None:
        super().__init__(config)
        self.target = torch.tensor(self.config.target, dtype=torch.float32, device=self.device).expand(self.num_envs, 3)

    def spawn_distribution(self) -> Spawn:
        return Spawn.around(self.config.target, self.config.spawn_half_width, clearance=0.3)

    def distance(self) -> torch.Tensor:
        return (self.state.pos - self.target).norm(dim=1)

    def get_observation(self) -> dict[str, torch.Tensor]:
        return {"state": self.state_vector(self.target), **self.frame.images}

    def get_success(self) -> torch.Tensor:
        return torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)

    def get_failure(self) -> torch.Tensor:
        return super().get_failure() | (self.distance().detach() > self.config.max_distance)

    def get_reward(self) -> torch.Tensor:
        s = self.state
        reward = 1.0 - 0.5 * self.distance() - 0.05 * s.vel.norm(dim=1) - 0.02 * s.omega.norm(dim=1)
        return reward - self.config.fail_penalty * self.failure.float()
