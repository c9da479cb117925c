"""Differentiability: gradcheck of one control step, long-rollout gradients against finite
differences, gradients through airframe parameters, batch independence, float32 against float64."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from visfly_dist.dynamics import DynamicsConfig, Quadrotor, load_airframe
from visfly_dist.dynamics.rotations import quat_from_euler

F64 = torch.float64
N = 2


def _inputs(quad: Quadrotor, seed: int = 0) -> list[torch.Tensor]:
    """A generic flying state (away from the ground and rotor limits) and a non-hover action."""
    g = torch.Generator().manual_seed(seed)
    n = quad.num_agents
    pos = torch.rand(n, 3, generator=g, dtype=F64) + torch.tensor([0.0, 0.0, 2.0], dtype=F64)
    vel = torch.rand(n, 3, generator=g, dtype=F64) - 0.5
    quat = quat_from_euler(0.3 * (torch.rand(n, 3, generator=g, dtype=F64) - 0.5))
    omega = torch.rand(n, 3, generator=g, dtype=F64) - 0.5
    rotor = torch.full((n, 4), quad.hover_rotor_speed(), dtype=F64) + 50 * torch.rand(n, 4, generator=g, dtype=F64)
    action = quad.hover_action() + 0.1 * (torch.rand(n, 4, generator=g, dtype=F64) - 0.5)
    return [pos, vel, quat, omega, rotor, action]


@pytest.mark.parametrize("controller", ["srt", "ctbr", "lv", "ps"])
def test_gradcheck_one_control_step(controller):
    quad = Quadrotor(DynamicsConfig(controller=controller, position_origin=(0.5, 0.5, 2.5)), num_agents=N, dtype=F64)
    inputs = [x.requires_grad_() for x in _inputs(quad)]

    def one_step(pos, vel, quat, omega, rotor, action):
        s = quad.step(quad.initial_state(pos=pos, vel=vel, quat=quat, omega=omega, rotor=rotor), action)
        return s.pos, s.vel, s.quat, s.omega, s.rotor

    # The full Jacobian for CTBR; random projections (gradcheck's fast mode) for the others.
    assert torch.autograd.gradcheck(one_step, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=controller != "ctbr")


def test_gradcheck_through_airframe_parameters():
    base = load_airframe("visfly")
    pos, vel, quat, omega, rotor, action = _inputs(Quadrotor(DynamicsConfig(controller="ctbr"), base,
                                                             num_agents=N, dtype=F64))

    def one_step(mass, drag_linear, drag_area, inertia):
        af = dataclasses.replace(base, mass=mass, drag_linear=drag_linear, drag_area=drag_area, inertia=inertia)
        quad = Quadrotor(DynamicsConfig(controller="ctbr"), af, num_agents=N, dtype=F64)
        s = quad.step(quad.initial_state(pos=pos, vel=3 * vel, quat=quat, omega=omega, rotor=rotor), action)
        return s.pos, s.vel, s.omega

    params = [torch.tensor(x, dtype=F64, requires_grad=True)
              for x in (base.mass, base.drag_linear, base.drag_area, base.inertia)]
    assert torch.autograd.gradcheck(one_step, params, eps=1e-8, atol=1e-5, rtol=1e-4)


def _rollout_loss(action0: torch.Tensor, vel0: torch.Tensor, mass: torch.Tensor, steps: int = 50) -> torch.Tensor:
    af = dataclasses.replace(load_airframe("visfly"), mass=mass)
    quad = Quadrotor(DynamicsConfig(controller="ctbr"), af, num_agents=N, dtype=F64)
    state = quad.initial_state(pos=torch.tensor([[0.0, 0.0, 3.0], [1.0, 0.0, 3.0]], dtype=F64), vel=vel0)
    later = (quad.hover_action() + torch.tensor([0.02, 0.1, -0.1, 0.05], dtype=F64)).expand(N, 4)
    for k in range(steps):
        # The first action is the variable; later ones are a fixed, gentle manoeuvre.
        action = action0 if k == 0 else later
        state = quad.step(state, action)
    weights = torch.tensor([1.0, -2.0, 0.5], dtype=F64)
    return (state.pos @ weights).sum() + 0.1 * state.vel.square().sum()


def test_fifty_step_rollout_gradient_matches_finite_differences():
    """Directional derivatives along random directions, by autograd and by central differences."""
    quad = Quadrotor(DynamicsConfig(controller="ctbr"), num_agents=N, dtype=F64)
    offsets = torch.tensor([[0.05, 0.2, -0.1, 0.1], [0.0, -0.3, 0.2, 0.0]], dtype=F64)
    action0 = quad.hover_action().expand(N, 4) + offsets
    vel0 = torch.tensor([[0.5, -0.2, 0.1], [0.0, 0.3, -0.2]], dtype=F64)
    mass = torch.tensor(0.46, dtype=F64)
    point = (action0, vel0, mass)
    args = [x.clone().requires_grad_() for x in point]
    grads = torch.autograd.grad(_rollout_loss(*args), args)
    g = torch.Generator().manual_seed(0)
    eps = 1e-6
    for i, (x, grad) in enumerate(zip(point, grads)):
        direction = torch.randn(x.shape, generator=g, dtype=F64)
        def moved(d: float) -> torch.Tensor:
            return _rollout_loss(*(y + d * direction if k == i else y for k, y in enumerate(point)))

        fd = (moved(eps) - moved(-eps)) / (2 * eps)
        assert float((grad * direction).sum()) == pytest.approx(float(fd), rel=1e-5, abs=1e-8), i


def test_agents_in_a_batch_are_independent():
    quad = Quadrotor(DynamicsConfig(controller="ps"), num_agents=4, dtype=F64)
    single = Quadrotor(DynamicsConfig(controller="ps"), num_agents=1, dtype=F64)
    pos, vel, quat, omega, rotor, action = (x.requires_grad_() for x in _inputs(quad, seed=1))
    state = quad.initial_state(pos=pos, vel=vel, quat=quat, omega=omega, rotor=rotor)
    for _ in range(10):
        state = quad.step(state, action)
    for i in range(4):
        alone = single.initial_state(pos=pos[i:i + 1], vel=vel[i:i + 1], quat=quat[i:i + 1],
                                     omega=omega[i:i + 1], rotor=rotor[i:i + 1])
        for _ in range(10):
            alone = single.step(alone, action[i:i + 1])
        assert torch.allclose(alone.pos, state.pos[i:i + 1], rtol=0, atol=1e-12)
        assert torch.allclose(alone.quat, state.quat[i:i + 1], rtol=0, atol=1e-12)
    # Agent 0's future depends on nothing of the other agents.
    grads = torch.autograd.grad(state.pos[0].sum() + state.quat[0].sum(), (pos, vel, omega, action))
    for g in grads:
        assert float(g[1:].abs().max()) == 0.0 and float(g[0].abs().max()) > 0.0


@pytest.mark.parametrize("controller", ["srt", "ctbr", "lv", "ps"])
def test_float32_and_float64_agree(controller):
    quads = {dt: Quadrotor(DynamicsConfig(controller=controller), num_agents=8, dtype=dt)
             for dt in (torch.float32, F64)}
    inputs = _inputs(quads[F64])
    states = {dt: q.initial_state(*(x.to(dt) for x in inputs[:5])) for dt, q in quads.items()}
    g = torch.Generator().manual_seed(3)
    action = quads[F64].hover_action() + 0.1 * (torch.rand(8, 4, generator=g, dtype=F64) - 0.5)
    for _ in range(50):
        states = {dt: q.step(states[dt], action.to(dt)) for dt, q in quads.items()}
    assert torch.allclose(states[torch.float32].pos.double(), states[F64].pos, atol=2e-4)
    assert torch.allclose(states[torch.float32].quat.double(), states[F64].quat, atol=2e-4)
