"""Landing: land on a black pad, seen by a downward RGB camera.

| observation | meaning                                                                  | unit             | range     |
|-------------|--------------------------------------------------------------------------|------------------|-----------|
| ``state``   | position minus pad centre (3), velocity (3), quaternion wxyz (4), body rates (3) | m, m/s, -, rad/s | unbounded |
| ``color``   | downward RGB image ``(3, 64, 64)``, 90 deg hfov                          | -                | [0, 255]  |
| ``pad``     | pad centre in the image by threshold segmentation: ``u``, ``v`` (image x right, y down, normalised), fraction of pad pixels | - | [-1, 1], [0, 1] |

The pad observation: pixels whose brightest channel is below ``pad_threshold`` are "pad"; ``u, v``
is their mean pixel position scaled to ``[-1, 1]`` (0, 0 at the image centre), the third entry the
fraction of the image they cover; all three are 0 when no pad pixel is seen.

Action: ``Box(-1, 1, (4,))`` for the configured controller (CTBR by default).

Reward per step, ``reward="ours"`` (default; ``p`` the point 0.1 m above the pad centre): ``0.05 *``
approach speed to ``p`` (m/s, finite difference), ``-0.01 * |omega|``, ``+0.01`` while the pad is
in view, ``+success_bonus`` (10) on success, ``-fail_penalty`` (5) on failure.
``reward="visfly"`` (VisFly's LandingEnv; ``c = (u, v) / 2`` the pad centre in VisFly's image units,
``T`` = ``max_episode_steps``, ``k`` the step): ``0.2 * min(1.25 - |c|, 1) - 0.2 * |(q_w, q_x)| +
0.2 * clamp(3 - z, 0, 3) / 3 - 0.02 |v| - 0.01 |omega| + 2 * success * (10 + T - k) / (1 + 2 |v|)``.

Termination: success when ``z <= 0.2 m``, within 0.3 m (horizontally) of the pad centre and
``|v| <= 0.3 m/s``; failure on collision (a hard or off-pad touch-down), out of bounds, or, with
``fail_when_pad_lost`` (off by default), when no pad pixel is in view. Truncation: 256 steps.
Spawn: uniform in ``pad + (0, 0, 2.5) ± (1, 1, 1)``, 0.3 m clear. The pad centre comes from the
scene metadata (``pad_center``) when present, else ``config.pad_center``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from gymnasium import spaces

from visfly_dist.client.config import EnvConfig
from visfly_dist.client.env_base import DroneEnvBase
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.tasks.common import metadata_point, progress_speed, reward_problem, vec3_problem

DOWNWARD = (math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0)
"""+90 deg pitch: the optical axis (body +x) turns to body -z, straight down when level."""

DOWNWARD_RGB = CameraSpec(name="color", kind="rgb", width=64, height=64, hfov_deg=90.0, rotation=DOWNWARD)


def pad_in_image(rgb: torch.Tensor, threshold: float) -> torch.Tensor:
    """``(N, 3)`` pad centre ``u, v`` in ``[-1, 1]`` and pad pixel fraction from RGB ``(N, 3, H, W)``."""
    dark = (rgb.amax(dim=1).float() < threshold).float()  # (N, H, W)
    n, h, w = dark.shape
    count = dark.sum(dim=(1, 2))
    us = (torch.arange(w, device=rgb.device, dtype=torch.float32) + 0.5) / w * 2 - 1
    vs = (torch.arange(h, device=rgb.device, dtype=torch.float32) + 0.5) / h * 2 - 1
    u = (dark.sum(dim=1) * us).sum(dim=1) / count.clamp(min=1)
    v = (dark.sum(dim=2) * vs).sum(dim=1) / count.clamp(min=1)
    return torch.stack((u, v, count / (h * w)), dim=1)


@dataclass
class LandingConfig(EnvConfig):
    """Landing settings; EnvConfig fields keep their meaning.

    Attributes:
        pad_center: pad centre when the scene's metadata has none, m.
        spawn_height: spawn centre height above the pad, m.
        spawn_half_width: spawn box half extents, m.
        pad_threshold: brightest channel below this is a pad pixel (0-255).
        fail_when_pad_lost: fail the episode when the pad leaves the view.
        success_bonus, fail_penalty: terminal reward terms (``reward="ours"``).
        brake_weight: weight of the braking term (``reward="ours"``): minus the speed above a safe
            speed that grows with the distance to the aim point, ``safe_speed + safe_speed_per_m * d``,
            so the drone is paid to slow down on the way in (0 turns it off).
        safe_speed, safe_speed_per_m: that safe speed at the aim point, m/s, and its growth, 1/s.
        reward: ``ours`` or ``visfly`` (the original's reward).
    """

    scenes: tuple[str, ...] = ("gen:landing-pad",)
    cameras: tuple[CameraSpec, ...] = (DOWNWARD_RGB,)
    pad_center: tuple[float, float, float] = (2.0, 0.0, 0.0)
    spawn_height: float = 2.5
    spawn_half_width: tuple[float, float, float] = (1.0, 1.0, 1.0)
    pad_threshold: float = 40.0
    fail_when_pad_lost: bool = False
    success_bonus: float = 10.0
    fail_penalty: float = 5.0
    brake_weight: float = 0.0
    safe_speed: float = 0.3
    safe_speed_per_m: float = 0.5
    reward: str = "ours"

    def problems(self) -> list[str]:
        out = super().problems() + vec3_problem("pad_center", self.pad_center) + reward_problem(self.reward)
        out += vec3_problem("spawn_half_width", self.spawn_half_width, positive=True)
        if not isinstance(self.pad_threshold, (int, float)) or not 0 < self.pad_threshold <= 255:
            out.append(f"pad_threshold={self.pad_threshold!r} must be in (0, 255]")
        if [c.kind for c in self.cameras[:1]] != ["rgb"]:
            out.append("landing needs an RGB camera first in cameras (e.g. the default DOWNWARD_RGB)")
        for name in ("brake_weight", "safe_speed", "safe_speed_per_m"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0 <= value < 1e3:
                out.append(f"{name}={value!r} must be a number in [0, 1000)")
        return out


class LandingEnv(DroneEnvBase):
    """Land gently on the pad."""

    config_class = LandingConfig
    config: LandingConfig

    def __init__(self, config: LandingConfig | None = None) -> None:
        super().__init__(config)
        self.pad = torch.zeros(self.num_envs, 3, device=self.device)
        self._prev_distance = torch.zeros(self.num_envs, device=self.device)

    def observation_space_dict(self) -> dict[str, spaces.Space]:
        out = super().observation_space_dict()
        out["pad"] = spaces.Box(np.array([-1, -1, 0], np.float32), np.ones(3, np.float32), dtype=np.float32)
        return out

    def spawn_positions(self, idx: torch.Tensor) -> torch.Tensor:
        # The spawn box follows each scene's pad, spawn_height above it.
        pads = np.array([self._pad_of(int(i)) for i in idx.tolist()]).reshape(-1, 3)
        return self.spawn_around(idx, pads + (0.0, 0.0, self.config.spawn_height), self.config.spawn_half_width, 0.3)

    def _pad_of(self, agent: int) -> np.ndarray:
        return metadata_point(self.scene_metadata(agent), "pad_center", self.config.pad_center)

    def reset_agents_hook(self, idx: torch.Tensor) -> None:
        pads = np.array([self._pad_of(int(i)) for i in idx.tolist()]).reshape(-1, 3)
        self.pad[idx] = torch.as_tensor(pads, dtype=torch.float32, device=self.device)
        self._prev_distance[idx] = self._aim_distance().detach()[idx]

    def _aim_distance(self) -> torch.Tensor:
        aim = self.pad + torch.tensor([0.0, 0.0, 0.1], device=self.device)
        return (self.state.pos - aim).norm(dim=1)

    def pad_observation(self) -> torch.Tensor:
        return pad_in_image(self.frame.images[self.cameras[0].name], self.config.pad_threshold)

    def get_observation(self) -> dict[str, torch.Tensor]:
        return {"state": self.state_vector(self.pad), "pad": self.pad_observation(), **self.frame.images}

    def get_success(self) -> torch.Tensor:
        s = self.state
        horizontal = (s.pos[:, :2] - self.pad[:, :2]).norm(dim=1)
        return ((s.pos[:, 2] <= 0.2) & (horizontal <= 0.3) & (s.vel.norm(dim=1) <= 0.3)).detach()

    def get_failure(self) -> torch.Tensor:
        failure = super().get_failure()
        if self.config.fail_when_pad_lost:
            failure = failure | (self.pad_observation()[:, 2] == 0)
        return failure

    def get_reward(self) -> torch.Tensor:
        cfg, s = self.config, self.state
        pad = self.pad_observation()
        if cfg.reward == "visfly":
            remaining = (cfg.max_episode_steps - self.episode_step).float()
            speed = s.vel.norm(dim=1)
            return (0.2 * (1.25 - 0.5 * pad[:, :2].norm(dim=1)).clamp(max=1.0) - 0.2 * s.quat[:, :2].norm(dim=1)
                    + 0.2 * (3.0 - s.pos[:, 2]).clamp(0.0, 3.0) / 3.0 - 0.02 * speed - 0.01 * s.omega.norm(dim=1)
                    + 2.0 * self.success.float() * (10.0 + remaining) / (1.0 + 2.0 * speed))
        distance = self._aim_distance()
        approach = progress_speed(self._prev_distance, distance, cfg.ctrl_dt)
        in_view = (pad[:, 2] > 0).float()
        too_fast = torch.relu(s.vel.norm(dim=1) - (cfg.safe_speed + cfg.safe_speed_per_m * distance))
        reward = 0.05 * approach - 0.01 * s.omega.norm(dim=1) + 0.01 * in_view - cfg.brake_weight * too_fast
        return reward + cfg.success_bonus * self.success.float() - cfg.fail_penalty * self.failure.float()

    def update_task_state(self) -> None:
        self._prev_distance = self._aim_distance().detach()
