"""Landing: land gently on a pad, seen by a downward camera (depth by default, or RGB).

| observation | meaning                                                                  | unit             | range     |
|-------------|--------------------------------------------------------------------------|------------------|-----------|
| ``state``   | position minus pad centre (3), velocity (3), quaternion wxyz (4), body rates (3) | m, m/s, -, rad/s | unbounded |
| ``depth``   | ``camera="depth"`` (default): downward depth image ``(1, 64, 64)``, 90 deg hfov | m           | [0, 20]   |
| ``color``   | ``camera="rgb"``: downward RGB image ``(3, 64, 64)``, 90 deg hfov       | -                | [0, 255]  |
| ``pad``     | pad centre in the image: ``u``, ``v`` (image x right, y down, normalised), and a third entry (below) | - | [-1, 1], [0, 1] |

The pad observation with ``camera="rgb"``: pixels whose brightest channel is below ``pad_threshold``
are "pad"; ``u, v`` is their mean pixel position scaled to ``[-1, 1]`` (0, 0 at the image centre),
the third entry the fraction of the image they cover; all three are 0 when no pad pixel is seen.
With ``camera="depth"`` the 1 cm pad hardly shows in depth, so it is located from the state and the
scene metadata: ``u, v`` is the pad centre projected into the camera (pinhole, differentiable), the
third entry 1 while that centre is in view, else 0 (and ``u, v`` are 0).

Action: ``Box(-1, 1, (4,))`` for the configured controller (CTBR by default).

Reward per step, ``reward="ours"`` (default; ``p`` the aim point 0.1 m above the pad centre, ``d``
the distance to it): ``0.05 *`` approach speed to ``p`` (m/s, finite difference), minus
``brake_weight`` (1) times the speed above ``safe_speed + safe_speed_per_m * d`` (0.2 + 0.5 d
m/s: the drone is paid to slow down on the way in, to 0.25 m/s at the top of the success zone),
minus ``centre_weight`` (0.5) times the descent speed times the horizontal distance to the pad
centre beyond 0.2 m (centre first, then descend), ``-0.01 * |omega|``, ``+0.01`` while the pad is
in view, ``+success_bonus`` (10) on success, ``-fail_penalty`` (5) on failure. Every term but the
terminal ones is differentiable in the state (BPTT/SHAC: :func:`shaped_reward`).
``reward="visfly"`` (VisFly's LandingEnv; ``c = (u, v) / 2`` the pad centre in VisFly's image units,
``T`` = ``max_episode_steps``, ``k`` the step): ``0.2 * min(1.25 - |c|, 1) - 0.2 * |(q_w, q_x)| +
0.2 * clamp(3 - z, 0, 3) / 3 - 0.02 |v| - 0.01 |omega| + 2 * success * (10 + T - k) / (1 + 2 |v|)``.

Termination: success when ``z <= 0.2 m``, within 0.3 m (horizontally) of the pad centre and
``|v| <= 0.3 m/s``; failure on collision (a hard or off-pad touch-down), out of bounds, or, with
``fail_when_pad_lost`` (off by default), when the pad is not in view. Truncation: 256 steps.
Spawn: uniform in ``pad + (0, 0, 2.5) ± (1, 1, 1)``, 0.3 m clear. The pad centre comes from the
scene metadata (``pad_center``) when present, else ``config.pad_center``.

Curriculum (on by default): the spawn box's height above the pad and its half widths are scaled
by ``curriculum_start`` (0.15: 0.31-0.53 m above the pad, ±0.15 m) at first; each time the agents
landed in at least ``curriculum_success`` (half) of the last :data:`CURRICULUM_WINDOW` (64) episodes,
the scale grows by ``(1 - curriculum_start) / curriculum_levels`` until the full box (after
``curriculum_levels`` (8) steps; 0 turns the curriculum off). Starts are drawn one episode ahead,
so a window's first episodes may come from the level before. ``visfly-dist eval`` turns it off
(:attr:`LandingConfig.evaluation_defaults`): evaluation always starts from the full box.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch
from gymnasium import spaces

from visfly_dist.client.config import EnvConfig
from visfly_dist.client.env_base import DroneEnvBase
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.tasks.common import metadata_point, progress_speed, reward_problem, sensed, to_body, vec3_problem

DOWNWARD = (math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0)
"""+90 deg pitch: the optical axis (body +x) turns to body -z, straight down when level."""

DOWNWARD_RGB = CameraSpec(name="color", kind="rgb", width=64, height=64, hfov_deg=90.0, rotation=DOWNWARD)
DOWNWARD_DEPTH = CameraSpec(name="depth", kind="depth", width=64, height=64, hfov_deg=90.0, rotation=DOWNWARD)
CAMERAS = {"rgb": DOWNWARD_RGB, "depth": DOWNWARD_DEPTH}
"""``LandingConfig.camera`` -> the default downward camera of that kind."""

CURRICULUM_WINDOW = 64
"""Episodes whose success rate moves the curriculum to its next level."""

CENTRED = 0.2
"""Horizontal distance to the pad centre, m, within which descending costs nothing (``centre_weight``)."""

AIM_HEIGHT = 0.1
"""The aim point of the approach term: this far above the pad centre, m (a drone resting on the pad)."""


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


def pad_projection(pos: torch.Tensor, quat: torch.Tensor, pad: torch.Tensor, hfov_deg: float) -> torch.Tensor:
    """``(N, 3)``: the pad centre projected into a :data:`DOWNWARD` camera (mounted at the body's
    centre), ``u, v`` in ``[-1, 1]`` as :func:`pad_in_image` gives them, then 1 when in view; ``u, v``
    are 0 when out of view. Differentiable in ``pos`` and ``quat`` where in view."""
    body = to_body(quat, pad - pos)
    depth = -body[:, 2]  # the optical axis is body -z; image x right is body -y, image y down body -x
    scale = math.tan(math.radians(hfov_deg) / 2) * depth.clamp(min=1e-6)
    uv = torch.stack((-body[:, 1], -body[:, 0]), dim=1) / scale[:, None]
    seen = (depth > 1e-6) & (uv.abs() <= 1).all(dim=1)
    uv = torch.where(seen[:, None], uv, torch.zeros_like(uv))
    return torch.cat((uv, seen[:, None].to(uv.dtype)), dim=1)


def shaped_reward(pos: torch.Tensor, vel: torch.Tensor, omega: torch.Tensor, aim: torch.Tensor,
                  prev_distance: torch.Tensor, in_view: torch.Tensor, dt: float, brake_weight: float,
                  safe_speed: float, safe_speed_per_m: float, centre_weight: float) -> torch.Tensor:
    """``(N,)`` the per-step terms of ``reward="ours"`` (no terminal terms); differentiable in the state.

    Args:
        pos, vel, omega: ``(N, 3)`` position (m), velocity (m/s), body rates (rad/s).
        aim: ``(N, 3)`` the aim point above the pad; ``prev_distance`` ``(N,)`` the last step's
            distance to it (a constant), m.
        in_view: ``(N,)`` 1 while the pad is seen.
        dt: control period, s. brake_weight, safe_speed, safe_speed_per_m: the braking term.
        centre_weight: weight of the off-centre descent term.
    """
    distance = (pos - aim).norm(dim=1)
    approach = progress_speed(prev_distance, distance, dt)
    too_fast = torch.relu(vel.norm(dim=1) - (safe_speed + safe_speed_per_m * distance))
    off_centre = torch.relu((pos[:, :2] - aim[:, :2]).norm(dim=1) - CENTRED)
    descending_off_centre = torch.relu(-vel[:, 2]) * off_centre
    return (0.05 * approach - 0.01 * omega.norm(dim=1) + 0.01 * in_view - brake_weight * too_fast
            - centre_weight * descending_off_centre)


@dataclass
class LandingConfig(EnvConfig):
    """Landing settings; EnvConfig fields keep their meaning.

    Attributes:
        camera: ``rgb`` or ``depth``: the kind of the downward camera (see the module docstring).
        cameras: ``None`` (default): the 64x64 downward camera of ``camera``'s kind; given
            explicitly, its first camera must be of that kind.
        pad_center: pad centre when the scene's metadata has none, m.
        spawn_height: spawn centre height above the pad, m.
        spawn_half_width: spawn box half extents, m.
        curriculum_levels: steps from the curriculum's first spawn box to the full one (0: no
            curriculum, always the full box).
        curriculum_start: the spawn box's scale at the curriculum's first level, in (0, 1].
        curriculum_success: success rate over the last ``CURRICULUM_WINDOW`` episodes that moves
            the curriculum to its next level, in (0, 1].
        pad_threshold: brightest channel below this is a pad pixel (0-255; ``camera="rgb"``).
        fail_when_pad_lost: fail the episode when the pad leaves the view.
        success_bonus, fail_penalty: terminal reward terms (``reward="ours"``).
        brake_weight: weight of the braking term (``reward="ours"``): minus the speed above a safe
            speed that grows with the distance to the aim point, ``safe_speed + safe_speed_per_m * d``,
            so the drone is paid to slow down on the way in (0 turns it off).
        safe_speed, safe_speed_per_m: that safe speed at the aim point, m/s, and its growth, 1/s.
        centre_weight: weight of the off-centre descent term (``reward="ours"``): minus the descent
            speed times the horizontal distance to the pad centre beyond ``CENTRED`` (0 turns it off).
        reward: ``ours`` or ``visfly`` (the original's reward).
    """

    evaluation_defaults: ClassVar[dict[str, Any]] = {"curriculum_levels": 0}
    """Settings an evaluation applies over the training run's: the full spawn box, from the start."""

    scenes: tuple[str, ...] = ("gen:landing-pad",)
    camera: str = "depth"
    cameras: tuple[CameraSpec, ...] | None = None  # type: ignore[assignment]
    pad_center: tuple[float, float, float] = (2.0, 0.0, 0.0)
    spawn_height: float = 2.5
    spawn_half_width: tuple[float, float, float] = (1.0, 1.0, 1.0)
    curriculum_levels: int = 8
    curriculum_start: float = 0.15
    curriculum_success: float = 0.5
    pad_threshold: float = 40.0
    fail_when_pad_lost: bool = False
    success_bonus: float = 10.0
    fail_penalty: float = 5.0
    brake_weight: float = 1.0
    safe_speed: float = 0.2
    safe_speed_per_m: float = 0.5
    centre_weight: float = 0.5
    reward: str = "ours"

    def __post_init__(self) -> None:
        if self.cameras is None:
            self.cameras = (CAMERAS[self.camera],) if self.camera in CAMERAS else ()
        super().__post_init__()

    def problems(self) -> list[str]:
        out = super().problems() + vec3_problem("pad_center", self.pad_center) + reward_problem(self.reward)
        out += vec3_problem("spawn_half_width", self.spawn_half_width, positive=True)
        if self.camera not in CAMERAS:
            out.append(f"camera={self.camera!r} must be one of {list(CAMERAS)}")
        elif [c.kind for c in (self.cameras or ())[:1]] != [self.camera]:
            out.append(f"camera={self.camera!r} needs a {self.camera} camera first in cameras "
                       f"(e.g. leave cameras unset for the 64x64 downward one)")
        if not isinstance(self.pad_threshold, (int, float)) or not 0 < self.pad_threshold <= 255:
            out.append(f"pad_threshold={self.pad_threshold!r} must be in (0, 255]")
        if not isinstance(self.curriculum_levels, int) or isinstance(self.curriculum_levels, bool) or self.curriculum_levels < 0:
            out.append(f"curriculum_levels={self.curriculum_levels!r} must be an int >= 0 (0: no curriculum)")
        for name in ("curriculum_start", "curriculum_success"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0 < value <= 1:
                out.append(f"{name}={value!r} must be a number in (0, 1]")
        for name in ("brake_weight", "safe_speed", "safe_speed_per_m", "centre_weight"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0 <= value < 1e3:
                out.append(f"{name}={value!r} must be a number in [0, 1000)")
        return out


class LandingEnv(DroneEnvBase):
    """Land gently on the pad.

    Attributes:
        pad: ``(N, 3)`` each agent's pad centre, m.
        curriculum_level: the curriculum's level, 0 to ``curriculum_levels``.
    """

    config_class = LandingConfig
    config: LandingConfig

    def __init__(self, config: LandingConfig | None = None) -> None:
        super().__init__(config)
        self.pad = torch.zeros(self.num_envs, 3, device=self.device)
        self._prev_distance = torch.zeros(self.num_envs, device=self.device)
        self.curriculum_level = 0
        self._outcomes: list[bool] = []  # success of the episodes ended at this level, the last CURRICULUM_WINDOW

    def observation_space_dict(self) -> dict[str, spaces.Space]:
        out = super().observation_space_dict()
        out["pad"] = spaces.Box(np.array([-1, -1, 0], np.float32), np.ones(3, np.float32), dtype=np.float32)
        return out

    def spawn_scale(self) -> float:
        """The spawn box's scale now: ``curriculum_start`` at level 0, 1 at the last level (or without curriculum)."""
        cfg = self.config
        if cfg.curriculum_levels == 0:
            return 1.0
        return cfg.curriculum_start + (1.0 - cfg.curriculum_start) * self.curriculum_level / cfg.curriculum_levels

    def spawn_positions(self, idx: torch.Tensor) -> torch.Tensor:
        # The spawn box follows each scene's pad, spawn_height above it, scaled by the curriculum.
        scale = self.spawn_scale()
        pads = np.array([self._pad_of(int(i)) for i in idx.tolist()]).reshape(-1, 3)
        half_width = [scale * w for w in self.config.spawn_half_width]
        return self.spawn_around(idx, pads + (0.0, 0.0, scale * self.config.spawn_height), half_width, 0.3)

    def _pad_of(self, agent: int) -> np.ndarray:
        return metadata_point(self.scene_metadata(agent), "pad_center", self.config.pad_center)

    def reset_agents_hook(self, idx: torch.Tensor) -> None:
        pads = np.array([self._pad_of(int(i)) for i in idx.tolist()]).reshape(-1, 3)
        self.pad[idx] = torch.as_tensor(pads, dtype=torch.float32, device=self.device)
        self._prev_distance[idx] = (self.state.pos.detach() - self._aim())[idx].norm(dim=1)

    def _aim(self) -> torch.Tensor:
        return self.pad + torch.tensor([0.0, 0.0, AIM_HEIGHT], device=self.device)

    def pad_observation(self) -> torch.Tensor:
        if self.config.camera == "depth":
            return pad_projection(self.state.pos, self.state.quat, self.pad, self.cameras[0].hfov_deg)
        return pad_in_image(sensed(self.frame).images[self.cameras[0].name], self.config.pad_threshold)

    def get_observation(self) -> dict[str, torch.Tensor]:
        return {"state": self.state_vector(self.pad), "pad": self.pad_observation(), **sensed(self.frame).images}

    def get_success(self) -> torch.Tensor:
        s = self.state
        horizontal = (s.pos[:, :2] - self.pad[:, :2]).norm(dim=1)
        return ((s.pos[:, 2] <= 0.2) & (horizontal <= 0.3) & (s.vel.norm(dim=1) <= 0.3)).detach()

    def get_failure(self) -> torch.Tensor:
        failure = super().get_failure()
        if self.config.fail_when_pad_lost:
            failure = failure | (self.pad_observation()[:, 2].detach() == 0)
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
        reward = shaped_reward(s.pos, s.vel, s.omega, self._aim(), self._prev_distance, (pad[:, 2] > 0).float(),
                               cfg.ctrl_dt, cfg.brake_weight, cfg.safe_speed, cfg.safe_speed_per_m, cfg.centre_weight)
        return reward + cfg.success_bonus * self.success.float() - cfg.fail_penalty * self.failure.float()

    def update_task_state(self) -> None:
        self._prev_distance = (self.state.pos.detach() - self._aim()).norm(dim=1)
        cfg = self.config
        if self.curriculum_level < cfg.curriculum_levels:
            ended = (self.success | self.failure | (self.episode_step >= cfg.max_episode_steps)) & self.step_mask
            self._outcomes = (self._outcomes + self.success[ended].tolist())[-CURRICULUM_WINDOW:]
            if len(self._outcomes) == CURRICULUM_WINDOW and sum(self._outcomes) >= cfg.curriculum_success * CURRICULUM_WINDOW:
                self.curriculum_level += 1
                self._outcomes = []
                print(f"landing curriculum: level {self.curriculum_level}/{cfg.curriculum_levels}, spawn box "
                      f"scale {self.spawn_scale():.2f}", file=sys.stderr, flush=True)
