"""The rigid-body quadrotor model and its integrators, on a flat component-major state.

The hot path works on one ``(17, N)`` tensor ``s`` whose rows are

    s[0:3] position (m, world)   s[3:6] velocity (m/s, world)   s[6:10] quaternion wxyz
    s[10:13] body rates (rad/s)  s[13:17] rotor speeds (rad/s)

Component-major rows keep every slice contiguous over the agents, so each torch op is one
vectorised loop over N and small constant matrices apply with one matmul. Mass and inertia are
folded into the constants: the model computes accelerations, never forces.

Model (Airframe docstring has the rotor layout):
    thrust T_i = a w_i^2 + b w_i + c
    collective acceleration = sum(T) / m along body z; angular acceleration = J^-1 (tau - w x J w)
    drag (body frame, on the velocity relative to the air) = -(k_lin + k_quad |v_b|) v_b / m
    gravity -9.81 m/s^2 along world z; rotor speed lag dw/dt = (w_cmd - w) / tau_motor
"""

from __future__ import annotations

from typing import Any

import torch

from visfly_dist.dynamics.airframe import Airframe

GRAVITY = 9.81
ROWS = (3, 3, 4, 3, 4)          # position, velocity, quaternion, body rates, rotor speeds
ROTOR_ROW = 13                   # first rotor row

# Rotor positions as multiples of arm_length / sqrt(2), and yaw-torque signs (PX4 quad X order).
ROTOR_X = (1.0, -1.0, 1.0, -1.0)
ROTOR_Y = (-1.0, 1.0, 1.0, -1.0)
ROTOR_YAW = (-1.0, -1.0, 1.0, 1.0)


def unpack(s: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Views ``(pos, vel, quat, omega, rotor)`` of a flat state (one split: one op in backward)."""
    return s.split(ROWS)


def _rotation_coeffs() -> torch.Tensor:
    """(9, 16) C with ``R.flatten() = C @ (q outer q).flatten()`` (homogeneous form of R(q))."""
    c = torch.zeros(3, 3, 4, 4, dtype=torch.float64)
    w, x, y, z = range(4)

    def put(i: int, j: int, terms: list[tuple[float, int, int]]) -> None:
        for coef, a, b in terms:
            c[i, j, a, b] += coef

    put(0, 0, [(1, w, w), (1, x, x), (-1, y, y), (-1, z, z)])
    put(1, 1, [(1, w, w), (-1, x, x), (1, y, y), (-1, z, z)])
    put(2, 2, [(1, w, w), (-1, x, x), (-1, y, y), (1, z, z)])
    put(0, 1, [(2, x, y), (-2, w, z)])
    put(1, 0, [(2, x, y), (2, w, z)])
    put(0, 2, [(2, x, z), (2, w, y)])
    put(2, 0, [(2, x, z), (-2, w, y)])
    put(1, 2, [(2, y, z), (-2, w, x)])
    put(2, 1, [(2, y, z), (2, w, x)])
    return c.reshape(9, 16)


def _quat_rate_coeffs() -> torch.Tensor:
    """(4, 12) Q with ``dq/dt = Q @ (q outer omega).flatten()``, i.e. ``0.5 q * (0, omega)``."""
    c = torch.zeros(4, 4, 3, dtype=torch.float64)
    w, x, y, z = range(4)
    for row, terms in enumerate((
        [(-1, x, 0), (-1, y, 1), (-1, z, 2)],
        [(1, w, 0), (1, y, 2), (-1, z, 1)],
        [(1, w, 1), (-1, x, 2), (1, z, 0)],
        [(1, w, 2), (1, x, 1), (-1, y, 0)],
    )):
        for coef, a, k in terms:
            c[row, a, k] = 0.5 * coef
    return c.reshape(4, 12)


class RigidBodyModel:
    """Constants and equations of motion of one airframe, for ``(k, N)`` component-major tensors.

    Args:
        airframe: physical parameters (floats or tensors; tensors keep their autograd graph; give a
            vector parameter as one tensor, not a list of tensors).
        motor_lag: integrate the rotor lag; otherwise rotor speeds are set to their command.
        wind: None, (3,) or (N, 3) world wind, m/s.
        device: torch device.
        dtype: float32 or float64.
    """

    def __init__(self, airframe: Airframe, motor_lag: bool, wind: torch.Tensor | None,
                 device: torch.device, dtype: torch.dtype) -> None:
        def t(x: object) -> torch.Tensor:
            return torch.as_tensor(x, dtype=dtype, device=device) if not isinstance(x, torch.Tensor) \
                else x.to(dtype=dtype, device=device)

        self.dtype, self.device = dtype, device
        mass = t(airframe.mass)
        inertia = t(airframe.inertia).reshape(3)
        a, b, c = (t(k) for k in airframe.thrust_coeffs)
        self.thrust_a, self.thrust_b, self.thrust_c = a, b, c
        rotor_min, rotor_max = (t(float(w)) for w in airframe.rotor_speed_range)
        self.thrust_min, self.thrust_max = self.thrust(rotor_min), self.thrust(rotor_max)
        self.mass = mass

        d = t(airframe.arm_length) / 2**0.5
        ones = torch.ones(4, dtype=dtype, device=device)
        torque = torch.stack((
            d * t(ROTOR_Y),                      # tau_x = sum(y_i T_i)
            -d * t(ROTOR_X),                     # tau_y = -sum(x_i T_i)
            t(airframe.yaw_torque_coeff) * t(ROTOR_YAW),
        ))
        # Thrusts (4, N) -> [collective acceleration; angular acceleration from rotor torques].
        self.mix = torch.cat(((ones / mass)[None], torque / inertia[:, None]))
        self.mix_inverse = torch.linalg.inv(self.mix)

        # omega_dot = J^-1 tau + G @ (omega outer omega), G = -J^-1 (omega x J omega) in outer form.
        j0, j1, j2 = inertia.unbind()
        pattern = torch.zeros(3, 3, 3, dtype=dtype, device=device)
        pattern[0, 1, 2] = pattern[1, 2, 0] = pattern[2, 0, 1] = 1.0
        coef = torch.stack(((j1 - j2) / j0, (j2 - j0) / j1, (j0 - j1) / j2))
        self.gyro = coef[:, None] * pattern.reshape(3, 9)

        self.rotation = _rotation_coeffs().to(dtype=dtype, device=device)
        self.quat_rate = _quat_rate_coeffs().to(dtype=dtype, device=device)
        self.dynamics_matrix, self.dynamics_bias = self._dynamics_matrix()
        self.drag_linear = -(t(airframe.drag_linear).reshape(3, 1) / mass)
        self.drag_quadratic = -(0.5 * t(airframe.air_density) * t(airframe.drag_area).reshape(3, 1) / mass)
        self.gravity = t((0.0, 0.0, -GRAVITY)).reshape(3, 1)
        self.unit_z = t((0.0, 0.0, 1.0)).reshape(3, 1)
        self.motor_lag = motor_lag
        self.inv_motor_tau = 1.0 / t(airframe.motor_time_constant) if motor_lag else t(0.0)
        self.wind = None if wind is None else wind.to(dtype=dtype, device=device).reshape(-1, 3).T.contiguous()

    # --- pieces -------------------------------------------------------------------------------

    def thrust(self, rotor: torch.Tensor) -> torch.Tensor:
        """Rotor thrusts, N, of rotor speeds (any shape), rad/s."""
        return torch.addcmul(self.thrust_c, rotor, rotor * self.thrust_a + self.thrust_b)

    def rotor_speed_for(self, thrust: torch.Tensor) -> torch.Tensor:
        """Rotor speeds (rad/s) giving ``thrust`` (N), after clamping it to what the rotors can give."""
        thrust = thrust.clamp(self.thrust_min, self.thrust_max)
        a, b, c = self.thrust_a, self.thrust_b, self.thrust_c
        half_b = b / (2 * a)
        return ((thrust - c) / a + half_b * half_b).sqrt() - half_b

    def rotation_matrix(self, quat: torch.Tensor) -> torch.Tensor:
        """(3, 3, N) body-to-world rotation of (4, N) quaternions (scaled by |q|^2)."""
        n = quat.shape[1]
        outer = (quat[:, None] * quat[None]).reshape(16, n)
        return (self.rotation @ outer).reshape(3, 3, n)

    def gyro_accel(self, omega: torch.Tensor) -> torch.Tensor:
        """(3, N) angular acceleration ``-J^-1 (omega x J omega)`` of body rates (3, N)."""
        return self.gyro @ (omega[:, None] * omega[None]).reshape(9, omega.shape[1])

    def drag_accel_body(self, rot: torch.Tensor, vel: torch.Tensor) -> torch.Tensor:
        """(3, N) body-frame drag acceleration at world velocity ``vel`` (3, N), given rotations."""
        if self.wind is not None:
            vel = vel - self.wind
        vel_body = (rot * vel[:, None]).sum(0)                      # R^T v
        return vel_body * torch.addcmul(self.drag_linear, self.drag_quadratic, vel_body.abs())

    def thrusts_for(self, collective: torch.Tensor, body_accel: torch.Tensor) -> torch.Tensor:
        """(4, N) rotor thrusts giving collective acceleration (1, N) and angular acceleration (3, N)
        from the rotors (unclamped)."""
        return self.mix_inverse @ torch.cat((collective, body_accel))

    # --- equations of motion ------------------------------------------------------------------

    def _dynamics_matrix(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(17, 57) D and (17, 1) d with ``D @ features(s) + d`` = [collective acc (1); angular acc (3);
        R flattened (9); dq/dt (4)], where ``features`` = [rotor (4); rotor^2 (4); x outer x (49)]
        and x = [quat; omega] (rows 6:13 of the state).

        Every bilinear term of the model (rotation matrix, quaternion rate, gyroscopic torque) and
        the thrust polynomial folded into the mixer: one matmul per derivative instead of four.
        """
        kw: dict[str, Any] = {"dtype": self.dtype, "device": self.device}
        matrix = torch.zeros(17, 57, **kw)
        matrix[0:4, 0:4] = self.mix * self.thrust_b
        matrix[0:4, 4:8] = self.mix * self.thrust_a
        outer = matrix[:, 8:].view(17, 7, 7)         # rows: x_i, columns: x_j
        outer[1:4, 4:7, 4:7] = self.gyro.reshape(3, 3, 3)
        outer[4:13, 0:4, 0:4] = self.rotation.reshape(9, 4, 4)
        outer[13:17, 0:4, 4:7] = self.quat_rate.reshape(4, 4, 3)
        bias = torch.zeros(17, 1, **kw)
        bias[0:4] = self.mix.sum(1, keepdim=True) * self.thrust_c
        return matrix, bias

    def derivative(self, s: torch.Tensor, rotor_cmd: torch.Tensor) -> torch.Tensor:
        """ds/dt (17, N) of the flat state ``s`` with rotor speed commands (4, N) held.

        Four small structured matmuls: cheapest in FLOPs (large batches, no grad, compiled).
        The adjoint (``dynamics.adjoint``) computes the same with one dense matmul of the dynamics
        matrix (fewer ops: small batches).
        """
        _, vel, quat, omega, rotor = unpack(s)
        wrench = self.mix @ self.thrust(rotor)                     # collective acc; angular acc
        rot = self.rotation_matrix(quat)
        force_body = torch.addcmul(self.drag_accel_body(rot, vel), self.unit_z, wrench[:1])
        accel = (rot * force_body[None]).sum(1) + self.gravity      # R f_b + g
        omega_dot = wrench[1:] + self.gyro_accel(omega)
        n = s.shape[1]
        quat_dot = self.quat_rate @ (quat[:, None] * omega[None]).reshape(12, n)
        rotor_dot = (rotor_cmd - rotor) * self.inv_motor_tau
        return torch.cat((vel, accel, quat_dot, omega_dot, rotor_dot))


def euler_step(model: RigidBodyModel, s: torch.Tensor, rotor_cmd: torch.Tensor, h: float) -> torch.Tensor:
    """One explicit Euler step of ``h`` seconds."""
    return torch.add(s, model.derivative(s, rotor_cmd), alpha=h)


def rk4_step(model: RigidBodyModel, s: torch.Tensor, rotor_cmd: torch.Tensor, h: float) -> torch.Tensor:
    """One classic fourth-order Runge-Kutta step of ``h`` seconds (rotor command held)."""
    f = model.derivative
    k1 = f(s, rotor_cmd)
    k2 = f(torch.add(s, k1, alpha=h / 2), rotor_cmd)
    k3 = f(torch.add(s, k2, alpha=h / 2), rotor_cmd)
    k4 = f(torch.add(s, k3, alpha=h), rotor_cmd)
    return torch.add(s, k1 + 2 * (k2 + k3) + k4, alpha=h / 6)

