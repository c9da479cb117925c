"""The four controllers: actions in [-1, 1]^4 to rotor speed commands.

Each controller maps an action linearly onto its physical range once per control step
(``prepare``), then computes rotor speed commands from the state at every physics substep
(``rotor_command``), as a flight controller's inner loop runs faster than the policy.

| controller | action[0]                  | action[1:3]               | action[3]               |
|------------|----------------------------|---------------------------|-------------------------|
| SRT        | rotor thrusts, each [0, T_max] N                                                 |
| CTBR       | collective [0, a_max] m/s^2 | body rates x, y +-max_rate rad/s | yaw rate +-max_rate |
| LV         | velocity x, y, z +-10 m/s (world)                      | yaw angle +-pi rad      |
| PS         | position x, y, z +-10 m from ``position_origin``       | yaw angle +-pi rad      |

CTBR runs a body-rate P-D loop whose error derivative is the measured angular acceleration (from
the rotor speeds). LV and PS run a velocity (PS: position-velocity cascade) loop giving a desired
acceleration, then the geometric SO(3) attitude controller of Lee, Leok and McClamroch (2010).
Commands become rotor thrusts through the inverse mixer, are clamped to what the rotors can give
(differentiable where unsaturated) and become rotor speeds through the inverse thrust map.

All tensors here are component-major: actions (4, N), states (17, N) (see ``model``).
"""

from __future__ import annotations

import math
from typing import Sequence

import torch

from visfly_dist.dynamics.airframe import Airframe
from visfly_dist.dynamics.model import GRAVITY, RigidBodyModel, unpack

LV_MAX_SPEED = 10.0
PS_MAX_OFFSET = 10.0


class Controller:
    """Base class: ``prepare`` once per control step, ``rotor_command`` once per substep."""

    def __init__(self, model: RigidBodyModel, airframe: Airframe) -> None:
        self.model = model

    def prepare(self, action: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Physical set points of actions (4, N) in [-1, 1]."""
        raise NotImplementedError

    def rotor_command(self, s: torch.Tensor, setpoint: tuple[torch.Tensor, ...]) -> torch.Tensor:
        """(4, N) rotor speed commands, rad/s, for flat state ``s`` (17, N)."""
        raise NotImplementedError

    def hover_action(self) -> list[float]:
        """The action that hovers in place (PS: at ``position_origin``), as four floats."""
        raise NotImplementedError

    def _rotor_speeds(self, collective: torch.Tensor, body_accel: torch.Tensor,
                      omega: torch.Tensor) -> torch.Tensor:
        """Rotor speeds for collective acceleration (1, N) and angular acceleration (3, N)."""
        from_rotors = body_accel - self.model.gyro_accel(omega)     # cancel the gyroscopic term
        return self.model.rotor_speed_for(self.model.thrusts_for(collective, from_rotors))


class SingleRotorThrust(Controller):
    """SRT: each action entry is one rotor's thrust, [-1, 1] -> [0, T_max]."""

    def prepare(self, action: torch.Tensor) -> tuple[torch.Tensor, ...]:
        thrust = (action + 1) * (0.5 * self.model.thrust_max)
        return (self.model.rotor_speed_for(thrust),)

    def rotor_command(self, s: torch.Tensor, setpoint: tuple[torch.Tensor, ...]) -> torch.Tensor:
        return setpoint[0]

    def hover_action(self) -> list[float]:
        hover = float(self.model.mass.detach()) * GRAVITY / 4
        return [2 * hover / float(self.model.thrust_max.detach()) - 1] * 4


class CollectiveThrustBodyRate(Controller):
    """CTBR: collective mass-normalised thrust and body rates, with a body-rate P-D loop.

    ``u = kp (w_des - w) - kd dw/dt`` is the commanded angular acceleration; ``dw/dt`` comes from the
    current rotor speeds. Without motor lag the rotors answer at once, ``dw/dt = u``, and the loop
    solves to ``u = kp / (1 + kd) (w_des - w)``.

    The loop is linear in ``[w; r; r^2; w outer w]`` (r the rotor speeds), so its rotor thrusts, and
    their square-root inverse, fold into one matrix: the inner loop is one matmul per substep.
    """

    def __init__(self, model: RigidBodyModel, airframe: Airframe) -> None:
        super().__init__(model, airframe)
        g = airframe.gains
        self.max_collective = float(airframe.max_collective_accel)
        self.max_rate = float(airframe.max_body_rate)
        kp = _column(g.rate_p, model).T                                     # (1, 3)
        kd = torch.as_tensor(g.rate_d, dtype=model.dtype, device=model.device)
        if not model.motor_lag:
            kp, kd = kp / (1 + kd), torch.zeros_like(kd)
        # Thrusts T = M0 c + M1 (kp (w_des - w) - kd (mix_1 T(r) + G ww) - G ww), with M = mix^-1;
        # kept as T' = (T - c0) / a, the form ``rotor_speed_for`` takes the square root of.
        m = model
        inv_a = 1 / m.thrust_a
        m0, m1 = m.mix_inverse[:, :1], m.mix_inverse[:, 1:]
        k = -kd * (m1 @ m.mix[1:])                                          # on the thrusts T(r)
        self.setpoint_matrix = inv_a * torch.cat((m0, m1 * kp), dim=1)      # on [c; w_des]
        self.state_matrix = inv_a * torch.cat((-m1 * kp, k * m.thrust_b, k * m.thrust_a,
                                               -(1 + kd) * (m1 @ m.gyro)), dim=1)
        self.state_bias = inv_a * m.thrust_c * (k.sum(1, keepdim=True) - 1)
        self.half_b = m.thrust_b * inv_a / 2
        self.low = (m.thrust_min - m.thrust_c) * inv_a
        self.high = (m.thrust_max - m.thrust_c) * inv_a

    def prepare(self, action: torch.Tensor) -> tuple[torch.Tensor, ...]:
        collective = (action[:1] + 1) * (0.5 * self.max_collective)
        command = torch.cat((collective, action[1:] * self.max_rate))
        return (torch.addmm(self.state_bias, self.setpoint_matrix, command),)

    def rotor_command(self, s: torch.Tensor, setpoint: tuple[torch.Tensor, ...]) -> torch.Tensor:
        _, omega, rotor = s.split((10, 3, 4))
        n = s.shape[1]
        features = torch.cat((omega, rotor, rotor * rotor, (omega[:, None] * omega[None]).reshape(9, n)))
        thrust = torch.addmm(setpoint[0], self.state_matrix, features)
        return (thrust.clamp(self.low, self.high) + self.half_b * self.half_b).sqrt() - self.half_b

    def hover_action(self) -> list[float]:
        return [2 * GRAVITY / self.max_collective - 1, 0.0, 0.0, 0.0]


class GeometricController(Controller):
    """Base of LV and PS: desired acceleration, then SO(3) attitude control (Lee et al. 2010).

    The desired thrust vector is ``A = a_des - g - a_drag`` (the model's drag at the current
    velocity is fed forward); collective ``= A . b3``; the desired attitude has ``b3_d = A / |A|`` and
    its heading from the yaw command; ``u = -kR e_R - kw omega`` with
    ``e_R = vee(R_d^T R - R^T R_d) / 2``. The desired acceleration is bounded (horizontal norm,
    vertical range) so the tilt stays moderate and the rotors keep authority for attitude.
    """

    def __init__(self, model: RigidBodyModel, airframe: Airframe) -> None:
        super().__init__(model, airframe)
        g = airframe.gains
        self.kv = _column(g.velocity_p, model)
        self.kx = _column(g.position_p, model)
        self.k_att = _column(g.attitude_p, model)
        self.k_rate = _column(g.attitude_d, model)
        self.max_horizontal = float(g.max_horizontal_accel)
        self.vertical_range = tuple(float(x) for x in g.vertical_accel_range)

    def velocity_setpoint(self, pos: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """(3, N) world velocity set point at positions (3, N) for the set point ``target``."""
        raise NotImplementedError

    def rotor_command(self, s: torch.Tensor, setpoint: tuple[torch.Tensor, ...]) -> torch.Tensor:
        target, heading = setpoint
        pos, vel, quat, omega, _ = unpack(s)
        accel = self.kv * (self.velocity_setpoint(pos, target) - vel)
        horizontal = accel[:2]
        norm = (horizontal.square().sum(0, keepdim=True) + 1e-12).sqrt()
        horizontal = horizontal * (self.max_horizontal / norm).clamp(max=1.0)
        vertical = accel[2:].clamp(*self.vertical_range)

        rot = self.model.rotation_matrix(quat)
        drag = (rot * self.model.drag_accel_body(rot, vel)[None]).sum(1)
        thrust_vec = torch.cat((horizontal, vertical)) - self.model.gravity - drag
        collective = (thrust_vec * rot[:, 2]).sum(0, keepdim=True)

        b3 = thrust_vec / thrust_vec.norm(dim=0, keepdim=True).clamp_min(1e-9)
        b2 = torch.linalg.cross(b3, heading, dim=0)
        b2 = b2 / b2.norm(dim=0, keepdim=True).clamp_min(1e-9)
        b1 = torch.linalg.cross(b2, b3, dim=0)
        rot_des = torch.stack((b1, b2, b3), dim=1)                  # columns b1, b2, b3
        err = (rot_des[:, :, None] * rot[:, None]).sum(0)           # R_d^T R
        e_rot = 0.5 * torch.stack((err[2, 1] - err[1, 2], err[0, 2] - err[2, 0], err[1, 0] - err[0, 1]))
        u = -self.k_att * e_rot - self.k_rate * omega
        return self._rotor_speeds(collective, u, omega)

    def hover_action(self) -> list[float]:
        return [0.0, 0.0, 0.0, 0.0]

    @staticmethod
    def _heading(yaw_action: torch.Tensor) -> torch.Tensor:
        yaw = yaw_action * math.pi
        return torch.stack((yaw.cos(), yaw.sin(), torch.zeros_like(yaw)))


class LinearVelocity(GeometricController):
    """LV: world velocity set point +-10 m/s per axis and yaw angle +-pi."""

    def prepare(self, action: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return action[:3] * LV_MAX_SPEED, self._heading(action[3])

    def velocity_setpoint(self, pos: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return target


class PositionYaw(GeometricController):
    """PS: world position set point ``origin +- 10 m`` per axis and yaw angle +-pi.

    The position loop gives the velocity set point ``kx (p_des - p)``.
    """

    def __init__(self, model: RigidBodyModel, airframe: Airframe, origin: Sequence[float]) -> None:
        super().__init__(model, airframe)
        self.origin = torch.as_tensor(origin, dtype=model.dtype, device=model.device).reshape(3, 1)

    def prepare(self, action: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return self.origin + action[:3] * PS_MAX_OFFSET, self._heading(action[3])

    def velocity_setpoint(self, pos: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return self.kx * (target - pos)


def make_controller(name: str, model: RigidBodyModel, airframe: Airframe,
                    position_origin: Sequence[float]) -> Controller:
    """The controller called ``name`` (validated by ``DynamicsConfig``)."""
    if name == "ps":
        return PositionYaw(model, airframe, position_origin)
    return {"srt": SingleRotorThrust, "ctbr": CollectiveThrustBodyRate, "lv": LinearVelocity}[name](model, airframe)


def _column(values: object, model: RigidBodyModel) -> torch.Tensor:
    return torch.as_tensor(values, dtype=model.dtype, device=model.device).reshape(-1, 1)
