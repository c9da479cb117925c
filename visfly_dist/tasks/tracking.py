"""Tracking: follow a target that moves on a circle, with a forward depth camera (after VisFly's TrackEnv).

| observation | meaning                                                                        | unit             | range     |
|-------------|--------------------------------------------------------------------------------|------------------|-----------|
| ``state``   | position minus the target (3), velocity (3), quaternion wxyz (4), body rates (3) | m, m/s, -, rad/s | unbounded |
| ``path``    | the target now and at the next ``future_points - 1`` instants ``future_dt`` apart, relative to the drone, body frame | m | unbounded |
| ``depth``   | forward depth image ``(1, 64, 64)``, 90 deg hfov, mounted 0.2 m forward (the target is not drawn) | m | [0, 20] |

Action: ``Box(-1, 1, (4,))`` for the configured controller (CTBR by default).

The target: ``c + r (cos(w t), sin(w t), 0)`` with ``t`` the episode time (``episode_step *
ctrl_dt``), ``c`` the scene metadata's ``track_center`` when it has one, else ``path_center``
((2, 0, 1) m); ``r`` = ``path_radius`` (2 m), ``w`` = ``path_speed`` (0.2 pi rad/s, 1.26 m/s).
Spawn: uniform in ``target(0) ± spawn_half_width`` ((0.3, 0.3, 0.2) m), 0.3 m clear.

Reward per step (``d`` distance to the target, ``v_t`` the target's velocity), differentiable in the
drone's state (BPTT/SHAC can use it): ``reward="ours"`` (default): ``1 - 0.5 d + near_weight *
exp(-(d / near_sigma)^2) - 0.1 |v - v_t| - 0.02 |omega|``, ``-fail_penalty`` (10) on failure. The
linear term pulls from afar; the Gaussian (weight 1, ``near_sigma`` 0.4 m) is steepest between 0.2
and 0.6 m, so it pulls hard across the success radius, where the linear term alone is flat. ``reward="visfly"`` (VisFly's TrackEnv):
``0.1 - (0.1 / 9) d - 1e-5 |q - q_level| - 0.002 |v| - 0.002 |omega|``.

Success: at the time limit, when the drone stayed within ``success_distance`` (0.5 m) of the target
for the last ``hold_fraction`` (40 %) of the episode. Termination: failure on collision, or out of
bounds (the scene's box, or farther than ``max_distance`` (3 m) from the target: it is lost).
Truncation: the time limit (256 steps of 0.03 s), with success or without: tracking could go on, so
a trainer values a successful end as it values a failed one (``success_ends_episode = False``).
"""  # noqa: E501

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from gymnasium import spaces

from visfly_dist.client.config import EnvConfig
from visfly_dist.client.env_base import DroneEnvBase
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.tasks.common import (
    held_steps,
    metadata_point,
    reward_problem,
    sensed,
    to_body,
    vec3_problem,
    visfly_hover_reward,
)
from visfly_dist.tasks.navigation import FORWARD_DEPTH


@dataclass
class TrackingConfig(EnvConfig):
    """Tracking settings (see the module docstring); EnvConfig fields keep their meaning.

    Attributes:
        path_center: circle centre when the scene's metadata has no ``track_center``, m.
        path_radius: circle radius, m.
        path_speed: angular speed of the target on the circle, rad/s (negative: clockwise).
        future_points: target positions observed (now and ahead).
        future_dt: time between observed target positions, s.
        spawn_half_width: spawn box half extents around the target's start, m.
        success_distance: success needs the drone this close to the target, m ...
        hold_fraction: ... for this share of ``max_episode_steps`` at the end of the episode.
        max_distance: the episode fails (out of bounds) beyond this distance from the target, m.
        fail_penalty: reward subtracted on failure (``reward="ours"``).
        near_weight: height of the Gaussian closeness term at the target (``reward="ours"``).
        near_sigma: width of the Gaussian closeness term, m (``reward="ours"``).
        reward: ``ours`` or ``visfly`` (the original's reward).
    """

    scenes: tuple[str, ...] = ("gen:empty",)
    cameras: tuple[CameraSpec, ...] = (FORWARD_DEPTH,)
    path_center: tuple[float, float, float] = (2.0, 0.0, 1.0)
    path_radius: float = 2.0
    path_speed: float = 0.2 * math.pi
    future_points: int = 10
    future_dt: float = 0.1
    spawn_half_width: tuple[float, float, float] = (0.3, 0.3, 0.2)
    success_distance: float = 0.5
    hold_fraction: float = 0.4
    max_distance: float = 3.0
    fail_penalty: float = 10.0
    near_weight: float = 1.0
    near_sigma: float = 0.4
    reward: str = "ours"

    def problems(self) -> list[str]:
        out = super().problems() + vec3_problem("path_center", self.path_center) + reward_problem(self.reward)
        out += vec3_problem("spawn_half_width", self.spawn_half_width, positive=True)
        for name in ("path_radius", "future_dt", "success_distance", "max_distance", "near_sigma"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not value > 0:
                out.append(f"{name}={value!r} must be a positive number")
        if not isinstance(self.path_speed, (int, float)) or not math.isfinite(self.path_speed):
            out.append(f"path_speed={self.path_speed!r} must be a finite number of rad/s")
        if not isinstance(self.future_points, int) or self.future_points < 1:
            out.append(f"future_points={self.future_points!r} must be an int >= 1")
        if not isinstance(self.near_weight, (int, float)) or not self.near_weight >= 0:
            out.append(f"near_weight={self.near_weight!r} must be a number >= 0")
        if not isinstance(self.hold_fraction, (int, float)) or not 0 < self.hold_fraction <= 1:
            out.append(f"hold_fraction={self.hold_fraction!r} must be in (0, 1]")
        return out


class TrackingEnv(DroneEnvBase):
    """Stay close to a target moving on a circle."""

    config_class = TrackingConfig
    success_ends_episode = False  # judged at the time limit: see the module docstring
    config: TrackingConfig

    def __init__(self, config: TrackingConfig | None = None) -> None:
        super().__init__(config)
        self.center = torch.tensor(self.config.path_center, dtype=torch.float32, device=self.device).repeat(self.num_envs, 1)
        self.held = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        self.hold_steps = math.ceil(self.config.hold_fraction * self.config.max_episode_steps)

    def observation_space_dict(self) -> dict[str, spaces.Space]:
        out = super().observation_space_dict()
        out["path"] = spaces.Box(-np.inf, np.inf, (self.config.future_points, 3), np.float32)
        return out

    def _center_of(self, agent: int) -> np.ndarray:
        return metadata_point(self.scene_metadata(agent), "track_center", self.config.path_center)

    def target_at(self, center: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """``(..., 3)`` target position at times ``t`` (s, shape ``(...)``) on circles around ``center``."""
        cfg = self.config
        phase = cfg.path_speed * t
        offset = torch.stack((torch.cos(phase), torch.sin(phase), torch.zeros_like(phase)), dim=-1)
        return center + cfg.path_radius * offset

    def time(self) -> torch.Tensor:
        """``(N,)`` episode time of each agent, s."""
        return self.episode_step.float() * self.config.ctrl_dt

    def target(self) -> torch.Tensor:
        """``(N, 3)`` where the target is now, m."""
        return self.target_at(self.center, self.time())

    def target_velocity(self) -> torch.Tensor:
        """``(N, 3)`` the target's velocity now, m/s."""
        cfg = self.config
        phase = cfg.path_speed * self.time()
        v = cfg.path_radius * cfg.path_speed
        return torch.stack((-v * torch.sin(phase), v * torch.cos(phase), torch.zeros_like(phase)), dim=1)

    def distance(self) -> torch.Tensor:
        """``(N,)`` distance to the target, m (differentiable in the drone's position)."""
        return (self.state.pos - self.target()).norm(dim=1)

    def spawn_positions(self, idx: torch.Tensor) -> torch.Tensor:
        # Around the target's start point of each scene.
        cfg = self.config
        starts = np.array([self._center_of(int(i)) for i in idx.tolist()]).reshape(-1, 3) + (cfg.path_radius, 0.0, 0.0)
        return self.spawn_around(idx, starts, cfg.spawn_half_width, clearance=0.3)

    def reset_agents_hook(self, idx: torch.Tensor) -> None:
        centers = np.array([self._center_of(int(i)) for i in idx.tolist()]).reshape(-1, 3)
        self.center[idx] = torch.as_tensor(centers, dtype=torch.float32, device=self.device)
        self.held[idx] = 0

    def out_of_bounds(self) -> torch.Tensor:
        """The scene's box, or farther than ``max_distance`` from the target (lost it)."""
        return super().out_of_bounds() | (self.distance().detach() > self.config.max_distance)

    def _held_now(self) -> torch.Tensor:
        return held_steps(self.held, self.distance().detach() <= self.config.success_distance)

    def get_observation(self) -> dict[str, torch.Tensor]:
        s, cfg = self.state, self.config
        ahead = torch.arange(cfg.future_points, device=self.device, dtype=torch.float32) * cfg.future_dt
        points = self.target_at(self.center[:, None], self.time()[:, None] + ahead)  # (N, K, 3)
        rel = points - s.pos[:, None]
        quat = s.quat[:, None].expand(-1, cfg.future_points, -1).reshape(-1, 4)
        path = to_body(quat, rel.reshape(-1, 3)).reshape(self.num_envs, cfg.future_points, 3)
        return {"state": self.state_vector(self.target()), "path": path, **sensed(self.frame).images}

    def get_success(self) -> torch.Tensor:
        at_end = self.episode_step >= self.config.max_episode_steps
        return at_end & (self._held_now() >= self.hold_steps)

    def get_reward(self) -> torch.Tensor:
        s, d = self.state, self.distance()
        if self.config.reward == "visfly":
            return visfly_hover_reward(s.quat, s.vel, s.omega, d)
        cfg = self.config
        near = cfg.near_weight * torch.exp(-(d / cfg.near_sigma) ** 2)
        reward = 1.0 - 0.5 * d + near - 0.1 * (s.vel - self.target_velocity()).norm(dim=1) - 0.02 * s.omega.norm(dim=1)
        return reward - cfg.fail_penalty * self.failure.float()

    def update_task_state(self) -> None:
        self.held = self._held_now()
