"""Racing: fly through a loop of gates, in order, as fast as possible (state-based).

| observation  | meaning                                                                   | unit             | range     |
|--------------|---------------------------------------------------------------------------|------------------|-----------|
| ``state``    | position minus the next gate (3), velocity (3), quaternion wxyz (4), body rates (3) | m, m/s, -, rad/s | unbounded |
| ``gates``    | the next two gates relative to the drone, in the body frame (2 rows of 3) | m                | unbounded |
| ``progress`` | gates passed in this episode / gates to pass (``laps * len(gates)``)      | -                | [0, 1]    |
| camera name  | one entry per configured camera (none by default)                         | see camera       | see camera |

Action: ``Box(-1, 1, (4,))`` for the configured controller (CTBR by default).

A gate is passed when the drone comes within ``gate_radius`` of its centre; the next one is then
the following gate of the loop. Reward per step, ``reward="ours"`` (default): ``0.05 *`` progress
speed toward the next gate (m/s, finite difference), ``+gate_bonus`` (1) per gate passed,
``-0.002 |omega|``, ``+success_bonus`` (10) on success, ``-fail_penalty`` (5) on failure.
``reward="visfly"`` (VisFly's RacingEnv; ``v_g`` velocity toward the next gate, ``v_p`` the rest of
the velocity, ``d`` the gate's distance): ``0.02 * min(v_g, 15) - 0.02 |v_p| / (d + 1) + 5 *``
gate passed ``- 0.001 |omega|``, no terminal terms. Termination: success after ``laps`` laps; failure on collision,
inside an obstacle or out of bounds. Truncation: 512 steps. Spawn: uniform in ``spawn_center ±
spawn_half_width``, 0.3 m clear.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from gymnasium import spaces

from visfly_dist.client.config import EnvConfig
from visfly_dist.client.env_base import DroneEnvBase, Spawn
from visfly_dist.tasks.common import approach_speed, progress_speed, reward_problem, sensed, to_body, vec3_problem

DEFAULT_GATES = ((3.0, 0.0, 1.5), (5.0, 3.0, 2.0), (3.0, 6.0, 1.5), (0.0, 3.0, 1.0))


@dataclass
class RacingConfig(EnvConfig):
    """Racing settings; EnvConfig fields keep their meaning.

    Attributes:
        gates: gate centres of the loop, in order, world frame, m.
        gate_radius: a gate is passed within this distance of its centre, m.
        laps: loops to complete for success.
        spawn_center, spawn_half_width: spawn box, m.
        gate_bonus, success_bonus, fail_penalty: reward terms (``reward="ours"``).
        reward: ``ours`` or ``visfly`` (the original's reward).
    """

    scenes: tuple[str, ...] = ("gen:empty",)
    max_episode_steps: int = 512
    gates: tuple[tuple[float, float, float], ...] = DEFAULT_GATES
    gate_radius: float = 0.5
    laps: int = 1
    spawn_center: tuple[float, float, float] = (0.0, 0.0, 1.5)
    spawn_half_width: tuple[float, float, float] = (0.5, 0.5, 0.3)
    gate_bonus: float = 1.0
    success_bonus: float = 10.0
    fail_penalty: float = 5.0
    reward: str = "ours"

    def problems(self) -> list[str]:
        out = super().problems() + reward_problem(self.reward)
        if len(self.gates) < 2:
            out.append(f"gates={self.gates!r} must hold at least 2 gate centres")
        for i, g in enumerate(self.gates):
            out += vec3_problem(f"gates[{i}]", g)
        if not isinstance(self.laps, int) or self.laps < 1:
            out.append(f"laps={self.laps!r} must be an int >= 1")
        if not isinstance(self.gate_radius, (int, float)) or not self.gate_radius > 0:
            out.append(f"gate_radius={self.gate_radius!r} must be a positive number of metres")
        out += vec3_problem("spawn_center", self.spawn_center)
        out += vec3_problem("spawn_half_width", self.spawn_half_width, positive=True)
        return out


class RacingEnv(DroneEnvBase):
    """Pass the gates in order, ``laps`` times."""

    config_class = RacingConfig
    config: RacingConfig

    def __init__(self, config: RacingConfig | None = None) -> None:
        super().__init__(config)
        self.gates = torch.tensor(self.config.gates, dtype=torch.float32, device=self.device)
        self.total_gates = len(self.config.gates) * self.config.laps
        self.passed = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        self._prev_distance = torch.zeros(self.num_envs, device=self.device)

    def observation_space_dict(self) -> dict[str, spaces.Space]:
        out = super().observation_space_dict()
        out["gates"] = spaces.Box(-np.inf, np.inf, (2, 3), np.float32)
        out["progress"] = spaces.Box(0.0, 1.0, (1,), np.float32)
        return out

    def spawn_distribution(self) -> Spawn:
        return Spawn.around(self.config.spawn_center, self.config.spawn_half_width, clearance=0.3)

    def next_gate(self, ahead: int = 0, passed: torch.Tensor | None = None) -> torch.Tensor:
        """``(N, 3)`` centre of the gate ``ahead`` gates after the next one (after ``passed`` gates)."""
        passed = self.passed if passed is None else passed
        return self.gates[(passed + ahead) % len(self.gates)]

    def gate_distance(self, passed: torch.Tensor | None = None) -> torch.Tensor:
        """``(N,)`` distance to the next gate, m (differentiable)."""
        return (self.state.pos - self.next_gate(passed=passed)).norm(dim=1)

    def gate_reached(self) -> torch.Tensor:
        """``(N,)`` bool: the drone is within ``gate_radius`` of its next gate this step."""
        return self.gate_distance().detach() < self.config.gate_radius

    def passed_now(self) -> torch.Tensor:
        """``(N,)`` gates passed, counting the one reached this step."""
        return self.passed + self.gate_reached().long()

    def reset_agents_hook(self, idx: torch.Tensor) -> None:
        self.passed[idx] = 0
        self._prev_distance[idx] = self.gate_distance().detach()[idx]

    def get_observation(self) -> dict[str, torch.Tensor]:
        s, passed = self.state, self.passed_now()
        gates = torch.stack([to_body(s.quat, self.next_gate(k, passed) - s.pos) for k in (0, 1)], dim=1)
        progress = (passed.float() / self.total_gates).clamp(max=1.0)[:, None]
        return {"state": self.state_vector(self.next_gate(passed=passed)), "gates": gates, "progress": progress,
                **sensed(self.frame).images}

    def get_success(self) -> torch.Tensor:
        return self.passed_now() >= self.total_gates

    def get_reward(self) -> torch.Tensor:
        cfg, s = self.config, self.state
        if cfg.reward == "visfly":
            gate, d = self.next_gate(), self.gate_distance()
            v_g = approach_speed(s.pos, s.vel, gate)
            v_p = (s.vel - v_g[:, None] * (gate - s.pos) / (d[:, None] + 1e-6)).norm(dim=1)
            return (0.02 * v_g.clamp(max=15.0) - 0.02 * v_p / (d + 1.0) + 5.0 * self.gate_reached().float()
                    - 0.001 * s.omega.norm(dim=1))
        progress = progress_speed(self._prev_distance, self.gate_distance(), cfg.ctrl_dt)
        reward = 0.05 * progress + cfg.gate_bonus * self.gate_reached().float() - 0.002 * self.state.omega.norm(dim=1)
        return reward + cfg.success_bonus * self.success.float() - cfg.fail_penalty * self.failure.float()

    def update_task_state(self) -> None:
        self.passed = self.passed_now()
        self._prev_distance = self.gate_distance().detach()
