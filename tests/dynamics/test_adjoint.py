"""The hand-written reverse pass of the CTBR step (``dynamics.adjoint``) against autograd's."""

from __future__ import annotations

import pytest
import torch

from visfly_dist.dynamics import DynamicsConfig, Quadrotor
from visfly_dist.dynamics.rotations import quat_from_euler

F64 = torch.float64


def _start(n: int, seed: int) -> tuple[torch.Tensor, ...]:
    """Agents flying, tumbling, some touching the ground and some with saturating actions."""
    g = torch.Generator().manual_seed(seed)
    pos = torch.rand(n, 3, generator=g, dtype=F64) * torch.tensor([2.0, 2.0, 0.3], dtype=F64) - 0.02
    vel = 2 * torch.rand(n, 3, generator=g, dtype=F64) - 1
    quat = quat_from_euler(0.8 * (torch.rand(n, 3, generator=g, dtype=F64) - 0.5))
    omega = 2 * torch.rand(n, 3, generator=g, dtype=F64) - 1
    action = 2.4 * torch.rand(n, 4, generator=g, dtype=F64) - 1.2      # some outside [-1, 1]
    return pos, vel, quat, omega, action


@pytest.mark.parametrize("settings", [
    dict(),
    dict(integrator="euler"),
    dict(motor_lag=False),
    dict(wind=(1.0, -0.5, 0.2), ground=False),
    dict(sim_dt=0.01, ctrl_dt=0.03),
])
def test_adjoint_gradients_equal_autograd(settings):
    n = 16
    quads = {flag: Quadrotor(DynamicsConfig(controller="ctbr", adjoint=flag, **settings), num_agents=n, dtype=F64)
             for flag in (True, False)}
    assert quads[True]._adjoint is not None and quads[False]._adjoint is None
    results = {}
    for flag, quad in quads.items():
        pos, vel, quat, omega, action = (x.requires_grad_() for x in _start(n, seed=5))
        state = quad.initial_state(pos=pos, vel=vel, quat=quat, omega=omega)
        contacts = []
        for k in range(6):
            state = quad.step(state, action * (1 - 0.1 * k))
            contacts.append(state.ground_contact)
        w = torch.linspace(-1, 1, 13, dtype=F64)
        loss = (torch.cat((state.pos, state.vel, state.quat, state.omega), 1) * w).sum() + state.rotor.sum() * 1e-3
        results[flag] = (state, torch.stack(contacts), torch.autograd.grad(loss, (pos, vel, quat, omega, action)))
    fast, slow = results[True], results[False]
    assert torch.equal(fast[1], slow[1])
    assert torch.allclose(fast[0].pos, slow[0].pos, rtol=0, atol=1e-12)
    for a, b in zip(fast[2], slow[2]):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-9), (a - b).abs().max()


def test_adjoint_step_passes_gradcheck_and_keeps_the_graph_short():
    quad = Quadrotor(DynamicsConfig(controller="ctbr"), num_agents=3, dtype=F64)
    pos, vel, quat, omega, action = _start(3, seed=2)
    pos = pos + torch.tensor([0.0, 0.0, 1.0], dtype=F64)

    def one_step(p, v, a):
        s = quad.step(quad.initial_state(pos=p, vel=v, quat=quat, omega=omega), a)
        return s.pos, s.vel, s.quat

    inputs = [x.clone().requires_grad_() for x in (pos, vel, action.clamp(-0.9, 0.9))]
    assert torch.autograd.gradcheck(one_step, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)
    out = one_step(*inputs)[0]
    node, names = out.grad_fn, []
    while node is not None and len(names) < 50:
        names.append(type(node).__name__)
        node = node.next_functions[0][0] if node.next_functions else None
    assert any("CtbrStepFunction" in name for name in names)


def test_airframe_parameters_with_grad_take_the_autograd_path():
    import dataclasses
    from visfly_dist.dynamics import load_airframe

    def height(mass: torch.Tensor) -> tuple[torch.Tensor, Quadrotor]:
        quad = Quadrotor(DynamicsConfig(controller="ctbr"), dataclasses.replace(load_airframe("visfly"), mass=mass),
                         num_agents=2, dtype=F64)
        state = quad.initial_state(pos=torch.ones(2, 3, dtype=F64), vel=torch.full((2, 3), 3.0, dtype=F64))
        state = quad.step(state, quad.hover_action().expand(2, 4))
        return state.pos[:, 2].sum(), quad

    mass = torch.tensor(0.5, dtype=F64, requires_grad=True)
    z, quad = height(mass)
    assert quad._adjoint is None
    (grad,) = torch.autograd.grad(z, mass)
    eps = 1e-6
    fd = (height(torch.tensor(0.5 + eps, dtype=F64))[0] - height(torch.tensor(0.5 - eps, dtype=F64))[0]) / (2 * eps)
    assert float(grad) != 0 and float(grad) == pytest.approx(float(fd), rel=1e-5)



def test_adjoint_keeps_float32_and_matches_autograd():
    n = 8
    quads = {flag: Quadrotor(DynamicsConfig(controller="ctbr", adjoint=flag), num_agents=n) for flag in (True, False)}
    grads = {}
    for flag, quad in quads.items():
        pos, vel, quat, omega, action = (x.float().requires_grad_() for x in _start(n, seed=3))
        state = quad.step(quad.initial_state(pos=pos + 1, vel=vel, quat=quat, omega=omega), action)
        assert all(x.dtype == torch.float32 for x in (state.pos, state.vel, state.quat, state.omega, state.rotor))
        grads[flag] = torch.autograd.grad(state.pos.sum() + state.quat[:, 1].sum(), (pos, quat, action))
        assert all(g.dtype == torch.float32 for g in grads[flag])
    for a, b in zip(grads[True], grads[False]):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-5), (a - b).abs().max()


def test_steps_without_gradients_match_the_torch_path():
    """Without gradients the NumPy forward runs small batches: the same trajectory as torch's ops."""
    n = 16
    quads = {flag: Quadrotor(DynamicsConfig(controller="ctbr", adjoint=flag), num_agents=n) for flag in (True, False)}
    gen = torch.Generator().manual_seed(5)
    states = {flag: q.initial_state(torch.rand(n, 3, generator=gen) + torch.tensor([0.0, 0.0, 1.0])) for flag, q in quads.items()}
    states[False] = states[True]
    with torch.no_grad():
        for _ in range(50):
            action = torch.rand(n, 4, generator=gen) * 0.4 - 0.2
            states = {flag: quads[flag].step(states[flag], action) for flag in (True, False)}
    for name in ("pos", "vel", "quat", "omega"):
        torch.testing.assert_close(getattr(states[True], name), getattr(states[False], name), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(states[True].rotor, states[False].rotor, rtol=1e-5, atol=1e-2)


def test_steps_without_gradients_skip_the_autograd_node_and_equal_steps_with_it():
    """The direct NumPy call gives bit for bit the states of the autograd node, and records nothing;
    the native forward (when built) gives them up to float32 rounding."""
    n = 16
    quad = Quadrotor(DynamicsConfig(controller="ctbr"), num_agents=n)
    pos, vel, quat, omega, action = (x.float() for x in _start(n, seed=7))
    start = quad.initial_state(pos=pos + 1, vel=vel, quat=quat, omega=omega)
    with torch.no_grad():
        native = quad.step(start, action)
        quad._native = None
        plain = quad.step(start, action)
    recorded = quad.step(start, action.clone().requires_grad_())
    assert plain.pos.grad_fn is None and "CtbrStepFunction" in type(recorded.pos.grad_fn).__name__
    for name in ("pos", "vel", "quat", "omega", "rotor", "ground_contact"):
        assert torch.equal(getattr(plain, name), getattr(recorded, name)), name
        torch.testing.assert_close(getattr(native, name), getattr(plain, name), rtol=1e-6, atol=1e-5)
