"""The CTBR control step with a hand-written reverse pass: one autograd node per control step.

Autograd records every small op of a step (a few hundred per control step at four RK4 substeps),
and at small batches its per-node bookkeeping, not arithmetic, is the cost of a backward pass.
Here the forward runs without recording, keeps what the reverse pass needs, and the reverse pass
applies the vector-Jacobian products of each piece in turn, as plain batched tensor ops:

    prepare (action -> set point)  ->  per substep: CTBR inner loop -> RK4 or Euler of the model
    derivative -> ground reaction

All tensors are component-major, as in :mod:`visfly_dist.dynamics.model`. Gradients reach the input
state and the action; airframe parameters that require grad, and wind, take the autograd path
(``Quadrotor`` chooses). Derivatives agree with autograd's (tests compare them), including its
conventions at kinks (clamps pass the gradient on their closed interval, ``|x|`` has slope 0 at 0).
"""

from __future__ import annotations

from typing import Any

import torch
from torch.autograd.function import once_differentiable

from visfly_dist.dynamics.controllers import CollectiveThrustBodyRate
from visfly_dist.dynamics.model import ROTOR_ROW, RigidBodyModel

Cache = tuple[torch.Tensor, ...]


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
        self.m, self.c = model, controller
        self.substeps, self.h, self.rk4, self.ground = substeps, h, rk4, ground
        kw = dict(dtype=model.dtype, device=model.device)
        self.action_scale = torch.tensor([0.5 * controller.max_collective] + [controller.max_rate] * 3, **kw)[:, None]
        self.drag_slope_quadratic = 2 * model.drag_quadratic
        # Reverse of ``features = [r; r^2; x outer x]`` through the dynamics matrix D (17, 57):
        # the rotor part as one (8, 17) matmul, and d/dx of ``g_y . D (x outer x)`` as one
        # (7, 17 * 7) matmul on ``g_y outer x`` (the outer-product block of D, symmetrised).
        matrix = model.dynamics_matrix
        self.rotor_matrix_t = matrix[:, :8].T.contiguous()
        bilinear = matrix[:, 8:].reshape(17, 7, 7)
        self.pair_matrix = (bilinear + bilinear.transpose(1, 2)).permute(1, 0, 2).reshape(7, 17 * 7).contiguous()
        # The same for the CTBR loop's features [omega; r; r^2; omega outer omega] and matrix (4, 20).
        loop = controller.state_matrix
        self.loop_linear_t = loop[:, :11].T.contiguous()
        rates = loop[:, 11:].reshape(4, 3, 3)
        self.loop_pair_matrix = (rates + rates.transpose(1, 2)).permute(1, 0, 2).reshape(3, 4 * 3).contiguous()

    # --- pieces: forward with a cache, and their vector-Jacobian products -----------------------

    def derivative_vjp(self, cache: Cache, g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(grad of s, grad of the rotor command) for the output gradient ``g`` (17, N)."""
        m = self.m
        x, rotor, rot, rel, vb, force = cache
        n = g.shape[1]
        g_pos, g_acc, g_quat_dot, g_omega_dot, g_rotor_dot = g.split((3, 3, 4, 3, 4))
        g_force = (rot * g_acc[:, None]).sum(0)                          # R^T g
        g_rot = g_acc[:, None] * force[None]
        g_vb = g_force * torch.addcmul(m.drag_linear, self.drag_slope_quadratic, vb.abs())
        g_rot = g_rot + rel[:, None] * g_vb[None]
        g_vel = g_pos + (rot * g_vb[None]).sum(1)                        # R g_vb
        g_y = torch.cat((g_force[2:], g_omega_dot, g_rot.reshape(9, n), g_quat_dot))
        g_x = self.pair_matrix @ (g_y[:, None] * x[None]).reshape(17 * 7, n)
        g_r, g_r2 = (self.rotor_matrix_t @ g_y).split(4)
        g_cmd = m.inv_motor_tau * g_rotor_dot
        g_rotor = torch.addcmul(g_r - g_cmd, rotor, g_r2, value=2.0)
        g_s = torch.cat((torch.zeros_like(g_pos), g_vel, g_x, g_rotor))
        return g_s, g_cmd

    def command_vjp(self, cache: Cache, g_cmd: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(grad of s, grad of the set point) for the rotor command gradient ``g_cmd`` (4, N)."""
        c = self.c
        omega, rotor, thrust, root = cache
        n = g_cmd.shape[1]
        inside = (thrust >= c.low) & (thrust <= c.high)
        g_thrust = torch.where(inside, 0.5 * g_cmd / root, torch.zeros_like(g_cmd))
        g_omega, g_r, g_r2 = (self.loop_linear_t @ g_thrust).split((3, 4, 4))
        g_omega = torch.addmm(g_omega, self.loop_pair_matrix, (g_thrust[:, None] * omega[None]).reshape(12, n))
        g_rotor = torch.addcmul(g_r, rotor, g_r2, value=2.0)
        g_s = torch.cat((torch.zeros(10, n, dtype=g_cmd.dtype, device=g_cmd.device), g_omega, g_rotor))
        return g_s, g_thrust

    def integrate(self, s: torch.Tensor, cmd: torch.Tensor) -> tuple[torch.Tensor, list[Cache]]:
        h = self.h
        k1, c1 = self.m.derivative_and_cache(s, cmd)
        if not self.rk4:
            return torch.add(s, k1, alpha=h), [c1]
        k2, c2 = self.m.derivative_and_cache(torch.add(s, k1, alpha=h / 2), cmd)
        k3, c3 = self.m.derivative_and_cache(torch.add(s, k2, alpha=h / 2), cmd)
        k4, c4 = self.m.derivative_and_cache(torch.add(s, k3, alpha=h), cmd)
        return torch.add(s, k1 + 2 * (k2 + k3) + k4, alpha=h / 6), [c1, c2, c3, c4]

    def integrate_vjp(self, caches: list[Cache], g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.h
        if not self.rk4:
            g_s, g_cmd = self.derivative_vjp(caches[0], h * g)
            return g + g_s, g_cmd
        c1, c2, c3, c4 = caches
        g_s4, g_cmd = self.derivative_vjp(c4, (h / 6) * g)
        g_s3, g_c = self.derivative_vjp(c3, torch.add((h / 3) * g, g_s4, alpha=h))
        g_cmd = g_cmd + g_c
        g_s2, g_c = self.derivative_vjp(c2, torch.add((h / 3) * g, g_s3, alpha=h / 2))
        g_cmd = g_cmd + g_c
        g_s1, g_c = self.derivative_vjp(c1, torch.add((h / 6) * g, g_s2, alpha=h / 2))
        return g + g_s4 + g_s3 + g_s2 + g_s1, g_cmd + g_c

    # --- the control step --------------------------------------------------------------------------

    def forward(self, s: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, list[Any]]:
        """Step ``s`` (17, N) under clamped actions (4, N); returns the new state, ground contact and tape."""
        c = self.c
        command = torch.cat((action[:1] + 1, action[1:])) * self.action_scale
        setpoint = torch.addmm(c.state_bias, c.setpoint_matrix, command)
        contact = torch.zeros(s.shape[1], dtype=torch.bool, device=s.device)
        tape = []
        for _ in range(self.substeps):
            cmd, c_cache = self.c.command_and_cache(s, setpoint)
            if not self.m.motor_lag:
                s = torch.cat((s[:ROTOR_ROW], cmd))
            s, i_cache = self.integrate(s, cmd)
            z, vz = s[2].clone(), s[5].clone()
            contact = contact | (z <= 0)
            if self.ground:
                s = s.clone()
                s[2] = z.clamp_min(0.0)
                s[5] = torch.where(z < 0, vz.clamp_min(0.0), vz)
            tape.append((c_cache, i_cache, z, vz))
        return s, contact, tape

    def backward(self, tape: list[Any], g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(grad of the input state, grad of the clamped action) for the output state gradient ``g``."""
        g_setpoint = torch.zeros_like(g[:4])
        for c_cache, i_cache, z, vz in reversed(tape):
            if self.ground:
                g = g.clone()
                g[2] = torch.where(z >= 0, g[2], torch.zeros_like(z))
                g[5] = torch.where((z >= 0) | (vz >= 0), g[5], torch.zeros_like(vz))
            g, g_cmd = self.integrate_vjp(i_cache, g)
            if not self.m.motor_lag:
                g_cmd = g_cmd + g[ROTOR_ROW:]
                g = torch.cat((g[:ROTOR_ROW], torch.zeros_like(g_cmd)))
            g_s, g_sp = self.command_vjp(c_cache, g_cmd)
            g = g + g_s
            g_setpoint = g_setpoint + g_sp
        g_action = (self.c.setpoint_matrix.T @ g_setpoint) * self.action_scale
        return g, g_action


class CtbrStepFunction(torch.autograd.Function):
    """``(s, action) -> (s', contact)`` through :class:`CtbrStep`, one node in the autograd graph."""

    @staticmethod
    def forward(ctx: Any, s: torch.Tensor, action: torch.Tensor, step: CtbrStep) -> tuple[torch.Tensor, torch.Tensor]:
        out, contact, tape = step.forward(s, action)
        ctx.step, ctx.tape = step, tape
        ctx.mark_non_differentiable(contact)
        return out, contact

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, g: torch.Tensor, _contact: Any) -> tuple[torch.Tensor, torch.Tensor, None]:
        g_s, g_action = ctx.step.backward(ctx.tape, g)
        return g_s, g_action, None
