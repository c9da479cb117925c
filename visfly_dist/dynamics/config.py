"""``DynamicsConfig``: how the quadrotor batch is simulated and controlled."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Union

import torch

from visfly_dist.errors import ConfigError

CONTROLLERS = ("srt", "ctbr", "lv", "ps")
INTEGRATORS = ("rk4", "euler")


@dataclass(frozen=True)
class DynamicsConfig:
    """Simulation and control settings; every problem is reported at construction.

    Attributes:
        controller: ``"srt"`` (single-rotor thrusts), ``"ctbr"`` (collective thrust and body rates),
            ``"lv"`` (linear velocity and yaw) or ``"ps"`` (position and yaw).
        sim_dt: physics substep, s; must divide ``ctrl_dt``.
        ctrl_dt: control step (one ``Quadrotor.step``), s. The default, 0.03 s (33.3 Hz) with 5 ms
            substeps, is VisFly's (its ``Dynamics(dt=0.005, ctrl_dt=0.03)``) and the rate every shipped
            task was tuned at; ``EnvConfig`` takes its defaults from this class, so it is set here only.
        integrator: ``"rk4"`` (classic Runge-Kutta) or ``"euler"`` (explicit).
        motor_lag: first-order lag on rotor speeds; without it rotors reach their command at once.
        action_delay_s: actions take effect this many seconds late (a FIFO in the state); a multiple
            of ``ctrl_dt``.
        wind: constant world-frame wind, m/s: None, one ``(3,)`` vector for all agents, or an
            ``(N, 3)`` tensor, one per agent. Drag acts on the velocity relative to the air.
        ground: apply the ground reaction at ``z = 0`` (contact is reported either way).
        position_origin: world point, m, that PS actions are relative to.
        check_actions: check every action's shape and finiteness in ``step`` (one reduction).
        compile: run the control step through ``torch.compile`` (first steps compile, slowly).
        adjoint: with gradients, run the CTBR step as one autograd node with a hand-written reverse
            pass (``dynamics.adjoint``; about 5x faster at 100 agents). Used on the CPU up to 3,072 agents,
            unless compiling or differentiating airframe parameters; False forces plain autograd.
    """

    controller: str = "ctbr"
    sim_dt: float = 0.005
    ctrl_dt: float = 0.03
    integrator: str = "rk4"
    motor_lag: bool = True
    action_delay_s: float = 0.0
    wind: Optional[Union[Sequence[float], torch.Tensor]] = None
    ground: bool = True
    position_origin: Sequence[float] = (0.0, 0.0, 0.0)
    check_actions: bool = True
    compile: bool = False
    adjoint: bool = True

    def __post_init__(self) -> None:
        problems = self.problems()
        if problems:
            raise ConfigError("invalid DynamicsConfig: " + "; ".join(problems))

    def problems(self) -> list[str]:
        """Every problem with this configuration, as messages (empty when valid)."""
        out: list[str] = []
        if self.controller not in CONTROLLERS:
            out.append(f"unknown controller={self.controller!r}: use one of {list(CONTROLLERS)}")
        if self.integrator not in INTEGRATORS:
            out.append(f"unknown integrator={self.integrator!r}: use one of {list(INTEGRATORS)}")
        if not (self.sim_dt > 0 and self.ctrl_dt > 0):
            out.append(f"sim_dt={self.sim_dt} and ctrl_dt={self.ctrl_dt} must be > 0")
        elif _ratio(self.ctrl_dt, self.sim_dt) is None:
            out.append(f"sim_dt={self.sim_dt} must divide ctrl_dt={self.ctrl_dt} into a whole number "
                       f"of substeps (e.g. sim_dt={self.ctrl_dt / max(1, round(self.ctrl_dt / self.sim_dt))})")
        delay_ok = self.ctrl_dt > 0 and _ratio(self.action_delay_s, self.ctrl_dt, allow_zero=True) is not None
        if self.action_delay_s < 0 or not delay_ok:
            out.append(f"action_delay_s={self.action_delay_s} must be a non-negative multiple of "
                       f"ctrl_dt={self.ctrl_dt}")
        if len(tuple(self.position_origin)) != 3:
            out.append(f"position_origin={self.position_origin!r} must have 3 entries")
        if self.wind is not None:
            w = torch.as_tensor(self.wind)
            if not (w.shape == (3,) or (w.dim() == 2 and w.shape[1] == 3)):
                out.append(f"wind of shape {tuple(w.shape)} must be (3,) or (num_agents, 3)")
            elif not bool(torch.isfinite(w).all()):
                out.append("wind must be finite")
        return out

    @property
    def substeps(self) -> int:
        """Physics substeps per control step."""
        return _whole(_ratio(self.ctrl_dt, self.sim_dt), "sim_dt must divide ctrl_dt", self)

    @property
    def delay_steps(self) -> int:
        """Control steps of action delay (the length of ``QuadState.action_queue``)."""
        return _whole(_ratio(self.action_delay_s, self.ctrl_dt, allow_zero=True),
                      "action_delay_s must be a multiple of ctrl_dt", self)


def _whole(k: Optional[int], rule: str, config: DynamicsConfig) -> int:
    """``k``, a ratio ``validate()`` accepts; a ConfigError naming ``rule`` for one it refuses."""
    if k is None:
        raise ConfigError(f"{rule} (sim_dt={config.sim_dt}, ctrl_dt={config.ctrl_dt}, "
                          f"action_delay_s={config.action_delay_s})")
    return k


def _ratio(a: float, b: float, allow_zero: bool = False) -> Optional[int]:
    """``a / b`` when it is a whole number (>= 1, or >= 0 with ``allow_zero``), else None."""
    k = round(a / b)
    if k < (0 if allow_zero else 1) or not math.isclose(k * b, a, rel_tol=1e-9, abs_tol=1e-12):
        return None
    return k
