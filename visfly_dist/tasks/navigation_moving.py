"""Navigation among moving obstacles: the garage of :mod:`navigation` with stones that move.

Everything of :class:`~visfly_dist.tasks.navigation.NavigationEnv` holds (reward, termination,
spawn, goal); the scene is ``gen:garage-stones`` with ``moving`` stones on circles, polygons and
splines, and the observation adds the ``moving_nearest`` obstacles' states. They are computed here,
client side, from the scene metadata's ``moving_objects`` (the same motion functions the worker
moves them with) at the env's simulation time ``sim_time``: nothing extra travels on the wire.

| observation | meaning                                                                        | unit        | range |
|-------------|--------------------------------------------------------------------------------|-------------|-------|
| ``state``, ``depth``, ``target`` | as in navigation (the depth image shows the moving stones where they are) | | |
| ``moving``  | per nearest moving obstacle (``K = moving_nearest`` rows, nearest first, flat ``7K``): centre relative to the drone in the body frame (3), its velocity relative to the drone's in the body frame (3), 1 for a real row (0: padding when the scene has fewer than K) | m, m/s, - | unbounded |

"Nearest" is by distance from the drone to the obstacle's bounding sphere (centre distance minus
its bounding radius). Spawns keep 0.5 m clear of every moving stone's whole swept path.
"""  # noqa: E501

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from gymnasium import spaces

from visfly_dist.scenes.motion import Motion, motion_from_dict
from visfly_dist.scenes.scene import MOVING_KEY
from visfly_dist.tasks.common import to_body
from visfly_dist.tasks.navigation import NavigationConfig, NavigationEnv

MOVING_ROW = 7
"""Entries per obstacle row of the ``moving`` observation: relative position (3), velocity (3), valid."""


@dataclass(frozen=True)
class MovingStates:
    """The moving obstacles of every agent's scene at one instant, world frame, padded to ``M``.

    Attributes:
        position: ``(N, M, 3)`` m. velocity: ``(N, M, 3)`` m/s. acceleration: ``(N, M, 3)`` m/s^2.
        radius: ``(N, M)`` bounding radius, m. valid: ``(N, M)`` bool, False for padding.
    """

    position: torch.Tensor
    velocity: torch.Tensor
    acceleration: torch.Tensor
    radius: torch.Tensor
    valid: torch.Tensor


@dataclass
class MovingNavigationConfig(NavigationConfig):
    """Navigation settings plus the moving stones.

    Attributes:
        moving: moving stones in the generated garage (used when ``scenes`` is empty).
        moving_speed: their mean speed, m/s.
        moving_nearest: how many of the nearest moving obstacles the observation holds (``K``).
    """

    moving: int = 8
    moving_speed: float = 1.0
    moving_nearest: int = 3

    def __post_init__(self) -> None:
        if not self.scenes:
            self.scenes = (f"gen:garage-stones?density={self.density}&moving={self.moving}"
                           f"&moving_speed={self.moving_speed}",)
        super().__post_init__()

    def problems(self) -> list[str]:
        out = super().problems()
        if isinstance(self.moving, bool) or not isinstance(self.moving, int) or not 0 <= self.moving <= 100:
            out.append(f"moving={self.moving!r} must be an int in [0, 100]")
        if not isinstance(self.moving_speed, (int, float)) or not 0 < self.moving_speed <= 20:
            out.append(f"moving_speed={self.moving_speed!r} must be a number in (0, 20] m/s")
        if isinstance(self.moving_nearest, bool) or not isinstance(self.moving_nearest, int) or not 1 <= self.moving_nearest <= 32:
            out.append(f"moving_nearest={self.moving_nearest!r} must be an int in [1, 32]")
        return out


class MovingNavigationEnv(NavigationEnv):
    """Reach the goal through a garage whose stones move; see the module docstring."""

    config_class = MovingNavigationConfig
    config: MovingNavigationConfig

    def __init__(self, config: MovingNavigationConfig | None = None) -> None:
        self._motions: dict[str, list[tuple[Motion, float]]] = {}  # per scene source
        super().__init__(config)

    def observation_space_dict(self) -> dict[str, spaces.Space]:
        out = super().observation_space_dict()
        out["moving"] = spaces.Box(-np.inf, np.inf, (MOVING_ROW * self.config.moving_nearest,), np.float32)
        return out

    def get_observation(self) -> dict[str, torch.Tensor]:
        return {**super().get_observation(), "moving": self.moving_observation()}

    def scene_motions(self, agent: int) -> list[tuple[Motion, float]]:
        """The moving obstacles of the scene agent ``agent`` flies in: ``(motion, bounding radius)``
        from its metadata."""
        meta = self.aggregator.agent_metadata(agent)
        key = str(meta.get("source"))
        if key not in self._motions:
            self._motions[key] = [(motion_from_dict(m["motion"], f"moving_objects[{i}].motion"), float(m["radius"]))
                                  for i, m in enumerate(meta.get(MOVING_KEY, []))]
        return self._motions[key]

    def moving_states(self) -> MovingStates:
        """Every agent's scene's moving obstacles at ``sim_time``, padded to the most any scene has."""
        # agents of one slot may fly in two scenes while a swap takes over at their episode ends
        _, first, scene_of = np.unique(self.aggregator.agent_sources(), return_index=True, return_inverse=True)
        per_scene = [self.scene_motions(int(agent)) for agent in first]
        m = max(1, max(len(v) for v in per_scene))
        n = self.num_envs
        pos, vel, acc = np.zeros((n, m, 3)), np.zeros((n, m, 3)), np.zeros((n, m, 3))
        radius, valid = np.zeros((n, m)), np.zeros((n, m), bool)
        for scene, motions in enumerate(per_scene):
            rows = scene_of == scene
            for k, (motion, r) in enumerate(motions):
                st = motion.state(self.sim_time)
                pos[rows, k], vel[rows, k], acc[rows, k] = st.position, st.velocity, st.acceleration
                radius[rows, k], valid[rows, k] = r, True
        as_t = lambda a: torch.as_tensor(a, dtype=torch.float32, device=self.device)  # noqa: E731
        return MovingStates(as_t(pos), as_t(vel), as_t(acc), as_t(radius), torch.as_tensor(valid, device=self.device))

    def moving_observation(self) -> torch.Tensor:
        """``(N, 7K)``: the K nearest moving obstacles, relative, in the body frame (module docstring)."""
        s, k = self.state, self.config.moving_nearest
        moving = self.moving_states()
        pos, vel, radius, valid = moving.position, moving.velocity, moving.radius, moving.valid
        rel_pos = pos - s.pos[:, None, :]
        rel_vel = vel - s.vel[:, None, :]
        gap = torch.where(valid, rel_pos.detach().norm(dim=2) - radius, torch.full_like(radius, float("inf")))
        take = min(k, gap.shape[1])
        order = gap.topk(take, dim=1, largest=False).indices                       # (N, take), nearest first
        pick = lambda a: a.gather(1, order[:, :, None].expand(-1, -1, 3))  # noqa: E731
        quat = s.quat[:, None, :].expand(-1, take, -1).reshape(-1, 4)
        body_pos = to_body(quat, pick(rel_pos).reshape(-1, 3)).reshape(-1, take, 3)
        body_vel = to_body(quat, pick(rel_vel).reshape(-1, 3)).reshape(-1, take, 3)
        real = valid.gather(1, order).float()[:, :, None]
        rows = torch.cat((body_pos * real, body_vel * real, real), dim=2)
        if take < k:
            rows = torch.cat((rows, rows.new_zeros(rows.shape[0], k - take, MOVING_ROW)), dim=1)
        return rows.reshape(rows.shape[0], MOVING_ROW * k)
