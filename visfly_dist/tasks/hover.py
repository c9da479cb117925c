"""Hover: fly to a point and hold it (state-based, dense reward; quick to learn).

| observation | meaning                                                           | unit          | range    |
|-------------|-------------------------------------------------------------------|---------------|----------|
| ``state``   | position minus target (3), velocity (3), quaternion wxyz (4), body rates (3) | m, m/s, -, rad/s | unbounded |
| camera name | one entry per configured camera (none by default)                 | see camera    | see camera |

Action: ``Box(-1, 1, (4,))`` for the configured controller (CTBR by default).

Target: the scene metadata's ``goal`` when it has one (``gen:empty``: (1, 0, 1.5)), else
``config.target``. Spawn: uniform in ``target ± spawn_half_width``, 0.3 m clear of obstacles.

Reward per step (``d`` distance to the target, m), ``reward="ours"`` (default):
``1 - 0.5 d - 0.05 |v| - 0.02 |omega|``, and ``-fail_penalty`` (10) on failure.
``reward="visfly"`` (VisFly's HoverEnv): ``0.1 - (0.1 / 9) d - 1e-5 |q - q_level| - 0.002 |v| -
0.002 |omega|``, no terminal terms.

Success: at the time limit, when the drone stayed within ``success_radius`` (0.3 m) of the target
for the last ``hold_fraction`` (half) of the episode. Termination: failure on collision, or out of
bounds (the scene's box, or farther than ``max_distance`` (2 m) from the target). Truncation: the
time limit (``max_episode_steps``, 100 steps of 0.03 s), with success or without: hovering could go on,
so a trainer values a successful end as it values a failed one (``success_ends_episode = False``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from visfly_dist.client.config import EnvConfig
from visfly_dist.client.env_base import DroneEnvBase
from visfly_dist.tasks.common import held_steps, metadata_point, reward_problem, sensed, vec3_problem, visfly_hover_reward


@dataclass
class HoverConfig(EnvConfig):
    """Hover settings (see the module docstring); EnvConfig fields keep their meaning.

    Attributes:
        target: the point to hold when the scene's metadata has no ``goal``, world frame, m.
        spawn_half_width: spawn box half extents around the target, m.
        max_distance: the episode fails (out of bounds) beyond this distance from the target, m.
        success_radius: success needs the drone this close to the target, m.
        hold_fraction: ... for this share of ``max_episode_steps`` at the end of the episode.
        fail_penalty: reward subtracted on failure (``reward="ours"``).
        reward: ``ours`` or ``visfly`` (the original's reward).
    """

    scenes: tuple[str, ...] = ("gen:empty",)
    max_episode_steps: int = 100
    target: tuple[float, float, float] = (1.0, 0.0, 1.5)
    spawn_half_width: tuple[float, float, float] = (0.5, 0.5, 0.5)
    max_distance: float = 2.0
    success_radius: float = 0.3
    hold_fraction: float = 0.5
    fail_penalty: float = 10.0
    reward: str = "ours"

    def problems(self) -> list[str]:
        out = super().problems() + vec3_problem("target", self.target) + reward_problem(self.reward)
        out += vec3_problem("spawn_half_width", self.spawn_half_width, positive=True)
        for name in ("max_distance", "success_radius"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not value > 0:
                out.append(f"{name}={value!r} must be a positive number of metres")
        if not isinstance(self.hold_fraction, (int, float)) or not 0 < self.hold_fraction <= 1:
            out.append(f"hold_fraction={self.hold_fraction!r} must be in (0, 1]")
        return out


class HoverEnv(DroneEnvBase):
    """Hold a drone at its scene's goal (or ``config.target``)."""

    config_class = HoverConfig
    success_ends_episode = False  # judged at the time limit: see the module docstring
    config: HoverConfig

    def __init__(self, config: HoverConfig | None = None) -> None:
        super().__init__(config)
        self.target = torch.tensor(self.config.target, dtype=torch.float32, device=self.device).repeat(self.num_envs, 1)
        self.held = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        self.hold_steps = math.ceil(self.config.hold_fraction * self.config.max_episode_steps)

    def _target_of(self, agent: int) -> np.ndarray:
        return metadata_point(self.scene_metadata(agent), "goal", self.config.target)

    def spawn_positions(self, idx: torch.Tensor) -> torch.Tensor:
        # The spawn box follows each scene's target.
        targets = [self._target_of(int(i)) for i in idx.tolist()]
        return self.spawn_around(idx, np.array(targets), self.config.spawn_half_width, clearance=0.3)

    def reset_agents_hook(self, idx: torch.Tensor) -> None:
        targets = np.array([self._target_of(int(i)) for i in idx.tolist()]).reshape(-1, 3)
        self.target[idx] = torch.as_tensor(targets, dtype=torch.float32, device=self.device)
        self.held[idx] = 0

    def distance(self) -> torch.Tensor:
        """``(N,)`` distance to the target, m (differentiable)."""
        return (self.state.pos - self.target).norm(dim=1)

    def out_of_bounds(self) -> torch.Tensor:
        """The scene's box, or farther than ``max_distance`` from the target."""
        return super().out_of_bounds() | (self.distance().detach() > self.config.max_distance)

    def _held_now(self) -> torch.Tensor:
        return held_steps(self.held, self.distance().detach() <= self.config.success_radius)

    def get_observation(self) -> dict[str, torch.Tensor]:
        return {"state": self.state_vector(self.target), **sensed(self.frame).images}

    def get_success(self) -> torch.Tensor:
        at_end = self.episode_step >= self.config.max_episode_steps
        return at_end & (self._held_now() >= self.hold_steps)

    def get_reward(self) -> torch.Tensor:
        s, d = self.state, self.distance()
        if self.config.reward == "visfly":
            return visfly_hover_reward(s.quat, s.vel, s.omega, d)
        reward = 1.0 - 0.5 * d - 0.05 * s.vel.norm(dim=1) - 0.02 * s.omega.norm(dim=1)
        return reward - self.config.fail_penalty * self.failure.float()

    def update_task_state(self) -> None:
        self.held = self._held_now()
