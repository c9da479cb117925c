"""Cooperative gap crossing: a team of three drones passes one narrow gap in a wall.

| observation  | meaning                                                                   | unit             | range     |
|--------------|---------------------------------------------------------------------------|------------------|-----------|
| ``state``    | position minus own target (3), velocity (3), quaternion wxyz (4), body rates (3) | m, m/s, -, rad/s | unbounded |
| ``teammates``| per teammate (2 rows): its position minus mine (3), its velocity minus mine (3) | m, m/s       | unbounded |
| ``depth``    | forward depth image ``(1, 64, 64)``, 90 deg hfov (teammates are drawn)     | m                | [0, 20]   |
| ``target``   | unit direction to own target in the body frame (3), distance to it (1)    | -, m             | [-1, 1], >= 0 |
| ``gap``      | unit direction to the own gap point in the body frame (3), distance to it (1) | -, m         | [-1, 1], >= 0 |

Action: ``Box(-1, 1, (4,))`` per drone for the configured controller: LV by default (world velocity
set point, +-10 m/s per axis, and a yaw angle), so a short training budget goes to the team's
queueing through the gap rather than to attitude control; ``controller="ctbr"`` for body rates.

Targets: drone of rank ``r`` in its team flies to ``targets[r]`` of the scene metadata (default
``(13, {-2, 0, 2}, 1.5)``) and spawns in its lane: ``(2, target_y, 1.5) ± (1, 0.5, 0.5)``.

Gap point: ``(gap_x, gap_y, target_z)`` (the scene's ``gap_center`` at the own target's height).
Path distance: before the wall (``x < gap_x``) the distance to the gap point plus the gap point's
distance to the own target; past it, the distance to the own target.

Reward per step: ``0.05 *`` progress speed along the path distance (m/s), ``-0.01 / (d_o + 0.2)``
obstacle proximity, ``-0.05 *`` approach speed to an obstacle nearer than 1 m, ``-0.1 * max(0, 1 -
d_t)`` for a teammate nearer than ``d_t`` < 1 m, ``-0.002 |omega|``, ``+success_bonus`` (10) for
every member on team success, ``-fail_penalty`` (5) on own failure.

Termination: success when every member of the team is ``through_margin`` (1 m) past the wall
(``x > gap_x + 1``); failure on collision (with obstacles or a teammate: closer than two drone
radii), inside an obstacle, out of bounds. The team's episodes end together (others truncated).
Truncation: 256 steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from gymnasium import spaces

from visfly_dist.client.config import EnvConfig
from visfly_dist.client.multi_agent import MultiDroneEnvBase
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.tasks.common import TARGET_DIM, obstacle_terms, progress_speed, sensed, target_observation, vec3_problem
from visfly_dist.tasks.navigation import FORWARD_DEPTH

DEFAULT_TARGETS = ((13.0, -2.0, 1.5), (13.0, 0.0, 1.5), (13.0, 2.0, 1.5))


@dataclass
class GapCrossingConfig(EnvConfig):
    """Gap-crossing settings; EnvConfig fields keep their meaning.

    Attributes:
        targets: per team rank, the target when the scene's metadata has none, m.
        gap_x: x of the wall when the scene's metadata has no ``gap_center`` (the gap is then at y = 0), m.
        spawn_x, spawn_z: lane spawn centre x and height, m.
        spawn_half_width: lane spawn half extents, m.
        through_margin: a drone is through when ``x > gap_x + through_margin``, m.
        success_bonus, fail_penalty: terminal reward terms.
    """

    num_envs: int = 6
    agents_per_scene: int = 3
    multi_agent: bool = True
    # every scene's gap somewhere in y = ±1.5 m, a new wall every 10 team episodes in a scene: the
    # policy must find the gap, not remember one (evaluation with another seed meets unseen walls)
    scenes: tuple[str, ...] = ("gen:gap-walls?gap_y_spread=1.5",)
    swap_every_resets: int = 30
    controller: str = "lv"
    cameras: tuple[CameraSpec, ...] = (FORWARD_DEPTH,)
    targets: tuple[tuple[float, float, float], ...] = DEFAULT_TARGETS
    gap_x: float = 8.0
    spawn_x: float = 2.0
    spawn_z: float = 1.5
    spawn_half_width: tuple[float, float, float] = (1.0, 0.5, 0.5)
    through_margin: float = 1.0
    success_bonus: float = 10.0
    fail_penalty: float = 5.0

    def problems(self) -> list[str]:
        out = super().problems()
        for i, t in enumerate(self.targets):
            out += vec3_problem(f"targets[{i}]", t)
        if len(self.targets) < 1:
            out.append("targets must hold at least one target")
        out += vec3_problem("spawn_half_width", self.spawn_half_width, positive=True)
        return out


class GapCrossingEnv(MultiDroneEnvBase):
    """Teams of drones cross a gap, each to its own target."""

    config_class = GapCrossingConfig
    config: GapCrossingConfig

    def __init__(self, config: GapCrossingConfig | None = None) -> None:
        super().__init__(config)
        self.target = torch.zeros(self.num_envs, 3, device=self.device)
        self.gap_x = torch.full((self.num_envs,), float(self.config.gap_x), device=self.device)
        self.gap_point = torch.zeros(self.num_envs, 3, device=self.device)
        self._prev_distance = torch.zeros(self.num_envs, device=self.device)

    def observation_space_dict(self) -> dict[str, spaces.Space]:
        out = super().observation_space_dict()
        out["target"] = spaces.Box(-np.inf, np.inf, (TARGET_DIM,), np.float32)
        out["gap"] = spaces.Box(-np.inf, np.inf, (TARGET_DIM,), np.float32)
        return out

    def _targets_of(self, agent: int) -> np.ndarray:
        meta = self.scene_metadata(agent)
        targets = np.asarray(meta.get("targets", self.config.targets), dtype=np.float64).reshape(-1, 3)
        return targets[int(self.team_rank[agent]) % len(targets)]

    def spawn_positions(self, idx: torch.Tensor) -> torch.Tensor:
        # One lane per team rank, in front of that rank's target.
        cfg = self.config
        centres = [(cfg.spawn_x, float(self._targets_of(int(i))[1]), cfg.spawn_z) for i in idx.tolist()]
        return self.spawn_around(idx, np.array(centres), cfg.spawn_half_width, clearance=0.5)

    def reset_agents_hook(self, idx: torch.Tensor) -> None:
        for i in idx.tolist():
            self.target[i] = torch.as_tensor(self._targets_of(i), dtype=torch.float32)
            gap = self.scene_metadata(i).get("gap_center")
            gap_x, gap_y = (float(gap[0]), float(gap[1])) if gap is not None else (self.config.gap_x, 0.0)
            self.gap_x[i] = gap_x
            self.gap_point[i] = torch.tensor([gap_x, gap_y, float(self.target[i, 2])])
        self._prev_distance[idx] = self.path_distance().detach()[idx]

    def target_distance(self) -> torch.Tensor:
        return (self.state.pos - self.target).norm(dim=1)

    def path_distance(self) -> torch.Tensor:
        """``(N,)`` metres left on the path through the own gap point to the own target."""
        pos = self.state.pos
        via = (pos - self.gap_point).norm(dim=1) + (self.gap_point - self.target).norm(dim=1)
        return torch.where(pos[:, 0] < self.gap_x, via, self.target_distance())

    def get_observation(self) -> dict[str, torch.Tensor]:
        s = self.state
        return {"state": self.state_vector(self.target), "teammates": self.teammates_observation(),
                "target": target_observation(s.pos, s.quat, self.target),
                "gap": target_observation(s.pos, s.quat, self.gap_point), **sensed(self.frame).images}

    def get_success(self) -> torch.Tensor:
        through = self.state.pos[:, 0].detach() > self.gap_x + self.config.through_margin
        team = through.view(-1, self.team_size).all(dim=1)
        return team.repeat_interleave(self.team_size)

    def get_reward(self) -> torch.Tensor:
        s, cfg, frame = self.state, self.config, sensed(self.frame)
        distance = self.path_distance()
        progress = progress_speed(self._prev_distance, distance, cfg.ctrl_dt)
        proximity, approach = obstacle_terms(s.pos, s.vel, frame.nearest, frame.distance, cfg.search_radius)
        crowding = (1.0 - self.teammate_distance()).clamp(min=0.0)
        reward = 0.05 * progress - 0.01 * proximity - 0.05 * approach - 0.1 * crowding - 0.002 * s.omega.norm(dim=1)
        return reward + cfg.success_bonus * self.success.float() - cfg.fail_penalty * self.failure.float()

    def update_task_state(self) -> None:
        self._prev_distance = self.path_distance().detach()
