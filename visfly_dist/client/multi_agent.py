"""``MultiDroneEnvBase``: teams of drones sharing a scene, seeing and colliding with each other.

Agent ``i`` flies in scene slot ``i // agents_per_scene`` with the other agents of that slot as its
team. Workers render teammates into each other's images (``multi_agent=True``); inter-drone
collision is computed here in torch: two teammates closer than ``2 * drone_radius`` both collide.
A team's episodes end together: when any member's episode ends, the others are truncated (unless
they terminated too), so a team is always respawned as a whole.
"""

from __future__ import annotations

import numpy as np
import torch
from gymnasium import spaces

from visfly_dist.client.config import EnvConfig
from visfly_dist.client.env_base import DroneEnvBase

TEAMMATE_DIM = 6
"""Per teammate: its position minus mine (m), its velocity minus mine (m/s)."""


class MultiDroneEnvBase(DroneEnvBase):
    """Base class of multi-agent tasks (``multi_agent`` is forced on).

    Attributes:
        team_size: agents per scene.
        teammates: ``(N, team_size - 1)`` indices of each agent's teammates, in index order.
    """

    def __init__(self, config: EnvConfig | None = None) -> None:
        config = self.config_class() if config is None else config
        if not config.multi_agent:
            config = config.replace(multi_agent=True)
        self.team_size = config.agents_per_scene
        super().__init__(config)
        n, m = self.num_envs, self.team_size
        team_start = torch.arange(n, device=self.device) // m * m
        others = torch.stack([torch.cat((torch.arange(r), torch.arange(r + 1, m))) for r in range(m)]) if m > 1 \
            else torch.zeros(1, 0, dtype=torch.long)
        self.team_rank = torch.arange(n, device=self.device) % m
        self.teammates = team_start[:, None] + others.to(self.device)[self.team_rank]

    def observation_space_dict(self) -> dict[str, spaces.Space]:
        """Adds ``teammates``: ``(team_size - 1, 6)`` relative positions and velocities."""
        out = super().observation_space_dict()
        out["teammates"] = spaces.Box(-np.inf, np.inf, (self.team_size - 1, TEAMMATE_DIM), np.float32)
        return out

    def teammates_observation(self) -> torch.Tensor:
        """``(N, team_size - 1, 6)``: each teammate's position and velocity relative to mine."""
        pos, vel = self.state.pos, self.state.vel
        rel_pos = pos[self.teammates] - pos[:, None]
        rel_vel = vel[self.teammates] - vel[:, None]
        return torch.cat((rel_pos, rel_vel), dim=2)

    def teammate_distance(self) -> torch.Tensor:
        """``(N,)`` distance to the nearest teammate, metres (``inf`` without teammates)."""
        if self.team_size == 1:
            return torch.full((self.num_envs,), float("inf"), device=self.device)
        return (self.state.pos[self.teammates] - self.state.pos[:, None]).norm(dim=2).min(dim=1).values

    def drone_collision(self) -> torch.Tensor:
        """``(N,)`` bool: a teammate is closer than two drone radii."""
        return self.teammate_distance().detach() < 2.0 * self.config.drone_radius

    def get_failure(self) -> torch.Tensor:
        """Obstacle collision, inside an obstacle, out of bounds, or a collision with a teammate."""
        return super().get_failure() | self.drone_collision()

    def expand_resets(self, terminated: torch.Tensor, truncated: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """When one member's episode ends, the team's does: the others are truncated."""
        done = (terminated | truncated).view(-1, self.team_size).any(dim=1)
        team_done = done.repeat_interleave(self.team_size)
        return terminated, truncated | (team_done & ~terminated)
