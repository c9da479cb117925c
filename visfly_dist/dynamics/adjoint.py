"""The CTBR control step with a hand-written reverse pass: one autograd node per control step.

Autograd records every small op of a step (a few hundred per control step at four RK4 substeps),
and at small batches its per-node bookkeeping, not arithmetic, is the cost of a backward pass.
Here the whole control step, from the batch-first state components to the next ones (quaternion
renormalised), runs unrecorded on NumPy views of the CPU tensors (a NumPy op on a few hundred
numbers costs a third of a torch op's dispatch), keeps what the reverse pass needs, and the reverse
pass applies the vector-Jacobian products of each piece in turn:

    clamp and prepare (action -> set point)  ->  per substep: CTBR inner loop -> RK4 or Euler of
    the model derivative -> ground reaction  ->  quaternion renormalisation

Inside, tensors are component-major, as in :mod:`visfly_dist.dynamics.model`. Gradients reach the
input state and the action; airframe parameters that require grad, and other devices than the CPU,
take the autograd path (``Quadrotor`` chooses). Derivatives agree with autograd's (tests compare
them), including its conventions at kinks (clamps pass the gradient on their closed interval,
``|x|`` has slope 0 at 0).
"""

from __future__ import annotations

import contextlib
from functools import cache
from typing import Any

import numpy as np
import torch
from threadpoolctl import ThreadpoolController
from torch.autograd.function import once_differentiable

from visfly_dist.dynamics.controllers import CollectiveThrustBodyRate
from visfly_dist.dynamics.model import ROTOR_ROW, ROWS, RigidBodyModel

Cache = tuple[np.ndarray, ...]
SPLITS = np.cumsum(ROWS)[:-1].tolist()          # row boundaries of pos, vel, quat, omega, rotor


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().cpu().numpy()


@cache
def _blas() -> ThreadpoolController:
    """NumPy's BLAS, limited to one thread while a step of many agents runs: its matmuls here are tens of
    microseconds, and OpenBLAS's threads, waiting on a busy core, made them 20x slower (measured
    at 4,096 agents on a loaded 2-core machine)."""
    return ThreadpoolController().select(user_api="blas")


class CtbrStep:
    """Forward and reverse of one CTBR control step on a flat state ``(17, N)`` and action ``(4, N)``.

    Args:
        model: the rigid-body model (its constants must not require grad).
        controller: the CTBR controller built on ``model``.
        substeps: physics substeps per control step.
        h: substep length, s.
        rk4: RK4 (else explicit Euler).
        ground: apply the ground reaction after each substep.
    """

    def __init__(self, model: RigidBodyModel, controller: CollectiveThrustBodyRate, substeps: int, h: float,
                 rk4: bool, ground: bool) -> None:
        self.substeps, self.h, self.rk4, self.ground = substeps, h, rk4, ground
        self.motor_lag = model.motor_lag
        c = controller
        self.action_scale = np.array([[0.5 * c.max_collective]] + [[c.max_rate]] * 3, dtype=_np(model.mass).dtype)
        # The model derivative: D @ [r; r^2; x outer x] + d (see ``RigidBodyModel._dynamics_matrix``).
        self.matrix, self.bias = _np(model.dynamics_matrix), _np(model.dynamics_bias)
        self.drag_linear, self.drag_quadratic = _np(model.drag_linear), _np(model.drag_quadratic)
        self.drag_slope_quadratic = 2 * self.drag_quadratic
        self.gravity = _np(model.gravity)
        self.inv_motor_tau = float(model.inv_motor_tau)
        self.wind = None if model.wind is None else _np(model.wind)
        # The CTBR loop: thrust term T' = setpoint + L @ [omega; r; r^2; omega outer omega].
        self.loop, self.loop_bias, self.setpoint_matrix = _np(c.state_matrix), _np(c.state_bias), _np(c.setpoint_matrix)
        self.half_b, self.low, self.high = float(c.half_b), float(c.low), float(c.high)
        # Reverse of ``features = [r; r^2; x outer x]`` through D (17, 57): the rotor part as one
        # (8, 17) matmul, and d/dx of ``g_y . D (x outer x)`` as one (7, 17 * 7) matmul on
        # ``g_y outer x`` (the outer-product block of D, symmetrised).
        self.rotor_matrix_t = np.ascontiguousarray(self.matrix[:, :8].T)
        bilinear = self.matrix[:, 8:].reshape(17, 7, 7)
        self.pair_matrix = np.ascontiguousarray((bilinear + bilinear.transpose(0, 2, 1))
                                                .transpose(1, 0, 2).reshape(7, 17 * 7))
        # The same for the CTBR loop's features [omega; r; r^2; omega outer omega] and matrix (4, 20).
        self.loop_linear_t = np.ascontiguousarray(self.loop[:, :11].T)
        rates = self.loop[:, 11:].reshape(4, 3, 3)
        self.loop_pair_matrix = np.ascontiguousarray((rates + rates.transpose(0, 2, 1))
                                                     .transpose(1, 0, 2).reshape(3, 4 * 3))

    # --- pieces: forward with a cache, and their vector-Jacobian products -----------------------

    def command(self, s: np.ndarray, setpoint: np.ndarray) -> tuple[np.ndarray, Cache]:
        """Rotor commands (4, N) of the CTBR loop, and its cache: body rates, rotor speeds, the
        unclamped thrust term and the square root."""
        omega, rotor = s[10:13], s[13:17]
        n = s.shape[1]
        features = np.concatenate((omega, rotor, rotor * rotor, (omega[:, None] * omega[None]).reshape(9, n)))
        thrust = setpoint + self.loop @ features
        root = np.sqrt(np.clip(thrust, self.low, self.high) + self.half_b * self.half_b)
        return root - self.half_b, (omega, rotor, thrust, root)

    def command_vjp(self, cache: Cache, g_cmd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(grad of rows 10:17 of s, grad of the set point) for the rotor command gradient (4, N)."""
        omega, rotor, thrust, root = cache
        n = g_cmd.shape[1]
        g_thrust = np.where((thrust >= self.low) & (thrust <= self.high), 0.5 * g_cmd / root, 0.0)
        g_lin = self.loop_linear_t @ g_thrust
        g_omega = g_lin[:3] + self.loop_pair_matrix @ (g_thrust[:, None] * omega[None]).reshape(12, n)
        g_rotor = g_lin[3:7] + 2 * rotor * g_lin[7:]
        return np.concatenate((g_omega, g_rotor)), g_thrust

    def derivative(self, s: np.ndarray, cmd: np.ndarray) -> tuple[np.ndarray, Cache]:
        """ds/dt (17, N) with rotor commands ``cmd`` held, and the intermediates its reverse pass
        needs: ``x = [quat; omega]``, rotor speeds, rotation (3, 3, N), air-relative velocity, body
        velocity and body force (acceleration)."""
        n = s.shape[1]
        vel, x, rotor = s[3:6], s[6:13], s[13:17]
        features = np.concatenate((rotor, rotor * rotor, (x[:, None] * x[None]).reshape(49, n)))
        y = self.matrix @ features + self.bias
        rot = y[4:13].reshape(3, 3, n)
        rel = vel if self.wind is None else vel - self.wind
        vel_body = (rot * rel[:, None]).sum(0)                      # R^T v
        force_body = vel_body * (self.drag_linear + self.drag_quadratic * np.abs(vel_body))
        force_body[2] += y[0]                                       # + collective along body z
        out = np.empty_like(s)
        out[0:3] = vel
        out[3:6] = (rot * force_body[None]).sum(1) + self.gravity   # R f_b + g
        out[6:10] = y[13:17]
        out[10:13] = y[1:4]
        np.multiply(cmd - rotor, self.inv_motor_tau, out=out[13:17])
        return out, (x, rotor, rot, rel, vel_body, force_body)

    def derivative_vjp(self, cache: Cache, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(grad of s, grad of the rotor command) for the output gradient ``g`` (17, N)."""
        x, rotor, rot, rel, vb, force = cache
        n = g.shape[1]
        g_acc = g[3:6]
        g_force = (rot * g_acc[:, None]).sum(0)                          # R^T g
        g_vb = g_force * (self.drag_linear + self.drag_slope_quadratic * np.abs(vb))
        g_rot = g_acc[:, None] * force[None] + rel[:, None] * g_vb[None]
        g_y = np.concatenate((g_force[2:], g[10:13], g_rot.reshape(9, n), g[6:10]))
        g_cmd = self.inv_motor_tau * g[13:17]
        g_s = np.empty_like(g)
        g_s[0:3] = 0.0
        g_s[3:6] = g[0:3] + (rot * g_vb[None]).sum(1)                    # R g_vb
        g_s[6:13] = self.pair_matrix @ (g_y[:, None] * x[None]).reshape(17 * 7, n)
        g_r = self.rotor_matrix_t @ g_y
        g_s[13:17] = g_r[:4] - g_cmd + 2 * rotor * g_r[4:]
        return g_s, g_cmd

    def integrate(self, s: np.ndarray, cmd: np.ndarray) -> tuple[np.ndarray, list[Cache]]:
        h, f = self.h, self.derivative
        k1, c1 = f(s, cmd)
        if not self.rk4:
            return s + h * k1, [c1]
        k2, c2 = f(s + (h / 2) * k1, cmd)
        k3, c3 = f(s + (h / 2) * k2, cmd)
        k4, c4 = f(s + h * k3, cmd)
        return s + (h / 6) * (k1 + 2 * (k2 + k3) + k4), [c1, c2, c3, c4]

    def integrate_vjp(self, caches: list[Cache], g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h, f = self.h, self.derivative_vjp
        if not self.rk4:
            g_s, g_cmd = f(caches[0], h * g)
            return g + g_s, g_cmd
        c1, c2, c3, c4 = caches
        g_s4, g_cmd = f(c4, (h / 6) * g)
        g_s3, g_c = f(c3, (h / 3) * g + h * g_s4)
        g_cmd += g_c
        g_s2, g_c = f(c2, (h / 3) * g + (h / 2) * g_s3)
        g_cmd += g_c
        g_s1, g_c = f(c1, (h / 6) * g + (h / 2) * g_s2)
        return g + g_s4 + g_s3 + g_s2 + g_s1, g_cmd + g_c

    # --- the control step --------------------------------------------------------------------------

    def forward(self, s: np.ndarray, action: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[Any]]:
        """Step ``s`` (17, N) under actions (4, N), clamped here; returns the new state (quaternion
        renormalised), ground contact and the tape."""
        clamped = np.clip(action, -1.0, 1.0)
        command = np.concatenate((clamped[:1] + 1, clamped[1:])) * self.action_scale
        setpoint = self.loop_bias + self.setpoint_matrix @ command
        contact = np.zeros(s.shape[1], dtype=bool)
        tape: list[Any] = [action]
        for _ in range(self.substeps):
            cmd, c_cache = self.command(s, setpoint)
            if not self.motor_lag:
                s = np.concatenate((s[:ROTOR_ROW], cmd))
            s, i_cache = self.integrate(s, cmd)
            z, vz = s[2].copy(), s[5].copy()
            contact |= z <= 0
            if self.ground:
                np.maximum(z, 0.0, out=s[2])
                s[5] = np.where(z < 0, np.maximum(vz, 0.0), vz)
            tape.append((c_cache, i_cache, z, vz))
        norm = np.sqrt((s[6:10] * s[6:10]).sum(0))
        s[6:10] /= norm
        tape.append((s[6:10].copy(), norm))
        return s, contact, tape

    def backward(self, tape: list[Any], g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(grad of the input state, grad of the action) for the output state gradient ``g`` (17, N),
        which it overwrites."""
        action, *substeps, (quat, norm) = tape
        g_quat = g[6:10]
        g_quat -= quat * (quat * g_quat).sum(0)
        g_quat /= norm
        g_setpoint = np.zeros_like(g[:4])
        for c_cache, i_cache, z, vz in reversed(substeps):
            if self.ground:
                g[2] = np.where(z >= 0, g[2], 0.0)
                g[5] = np.where((z >= 0) | (vz >= 0), g[5], 0.0)
            g, g_cmd = self.integrate_vjp(i_cache, g)
            if not self.motor_lag:
                g_cmd += g[ROTOR_ROW:]
                g[ROTOR_ROW:] = 0.0
            g_s, g_sp = self.command_vjp(c_cache, g_cmd)
            g[10:17] += g_s
            g_setpoint += g_sp
        g_action = (self.setpoint_matrix.T @ g_setpoint) * self.action_scale
        g_action *= (action >= -1.0) & (action <= 1.0)
        return g, g_action


BLAS_SERIAL_MAX_AGENTS = 256
"""Up to this many agents a step's matmuls stay under OpenBLAS's threshold for threading
(m * n * k <= 4 * 65536)."""


def _one_blas_thread(n: int) -> Any:
    """A context that holds NumPy's BLAS to one thread for a step of ``n`` agents.

    Below ``BLAS_SERIAL_MAX_AGENTS`` the matmuls (17 x 57 by 57 x n at most) are under OpenBLAS's
    own threading threshold, so the limit (about 10 us to set and restore) is skipped.
    """
    return contextlib.nullcontext() if n <= BLAS_SERIAL_MAX_AGENTS else _blas().limit(limits=1)


def ctbr_step(pos: torch.Tensor, vel: torch.Tensor, quat: torch.Tensor, omega: torch.Tensor, rotor: torch.Tensor,
              action: torch.Tensor, step: CtbrStep) -> tuple[tuple[torch.Tensor, ...], list[Any]]:
    """One CTBR control step on batch-first CPU tensors, unrecorded: the next
    ``(pos, vel, quat, omega, rotor, contact)`` and the tape for :meth:`CtbrStep.backward`.

    Steps without gradients call it directly (``Quadrotor.step``, where the native forward of
    ``dynamics.native_step`` is not built), skipping ``autograd.Function``'s bookkeeping;
    :class:`CtbrStepFunction` wraps it with the reverse pass.
    """
    s = np.concatenate([x.detach().numpy() for x in (pos, vel, quat, omega, rotor)], axis=1).T
    with _one_blas_thread(s.shape[1]):
        out, contact, tape = step.forward(np.ascontiguousarray(s), np.ascontiguousarray(action.detach().numpy().T))
    out = np.ascontiguousarray(out.T)
    return (*(torch.from_numpy(x) for x in np.split(out, SPLITS, axis=1)), torch.from_numpy(contact)), tape


class CtbrStepFunction(torch.autograd.Function):
    """``(pos, vel, quat, omega, rotor, action) -> (pos', vel', quat', omega', rotor', contact)``, all
    batch-first CPU tensors, through :class:`CtbrStep`: one node in the autograd graph."""

    @staticmethod
    def forward(ctx: Any, pos: torch.Tensor, vel: torch.Tensor, quat: torch.Tensor, omega: torch.Tensor,
                rotor: torch.Tensor, action: torch.Tensor, step: CtbrStep) -> tuple[torch.Tensor, ...]:
        outputs, tape = ctbr_step(pos, vel, quat, omega, rotor, action, step)
        ctx.step, ctx.tape = step, tape
        ctx.mark_non_differentiable(outputs[-1])
        return outputs

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, *grads: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        g = np.concatenate([x.numpy() for x in grads[:5]], axis=1).T.copy()
        with _one_blas_thread(g.shape[1]):
            g_s, g_action = ctx.step.backward(ctx.tape, g)
        g_s = np.ascontiguousarray(g_s.T)
        return (*(torch.from_numpy(x) for x in np.split(g_s, SPLITS, axis=1)),
                torch.from_numpy(np.ascontiguousarray(g_action.T)), None)
