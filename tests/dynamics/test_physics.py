"""Physics of the rigid-body model: hover, free fall, torque signs, ground, wind, delay, integrators."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from visfly_dist.dynamics import DynamicsConfig, QuadState, Quadrotor, load_airframe
from visfly_dist.dynamics.model import GRAVITY
from visfly_dist.dynamics.rotations import euler_from_quat

F64 = torch.float64


def _quad(controller: str = "srt", n: int = 1, airframe="visfly", dtype=F64, **cfg) -> Quadrotor:
    return Quadrotor(DynamicsConfig(controller=controller, **cfg), airframe, num_agents=n, dtype=dtype)


def _at(*xyz: float, n: int = 1, dtype=F64) -> torch.Tensor:
    return torch.tensor([xyz] * n, dtype=dtype)


@pytest.mark.parametrize("airframe", ["visfly", "visfly-large"])
@pytest.mark.parametrize("controller", ["srt", "ctbr", "lv", "ps"])
def test_hover_action_holds_position_for_two_seconds(controller, airframe):
    origin = (1.0, -2.0, 1.5)
    quad = Quadrotor(DynamicsConfig(controller=controller, position_origin=origin), airframe, num_agents=2)
    start = torch.tensor([origin, origin])
    state = quad.initial_state(pos=start)
    action = quad.hover_action().expand(2, 4)
    assert bool((action.abs() < 0.9).all()), f"hover action {action[0].tolist()} should sit well inside [-1, 1]"
    for _ in range(round(2.0 / quad.config.ctrl_dt)):
        state = quad.step(state, action)
        assert float((state.pos - start).norm(dim=1).max()) < 1e-3
    assert not bool(state.ground_contact.any())


def _zero_drag(name: str = "visfly"):
    af = load_airframe(name)
    return dataclasses.replace(af, drag_linear=(0.0, 0.0, 0.0), drag_area=(0.0, 0.0, 0.0))


def test_free_fall_from_rest_matches_g_t2_over_2():
    # SRT action -1 commands exactly zero thrust (T(200 rad/s) < 0, so zero is reachable); without
    # motor lag the rotors get there at once, and the airframe copy has no drag.
    quad = _quad("srt", airframe=_zero_drag(), motor_lag=False, ground=False)
    state = quad.initial_state(pos=_at(0.5, -0.3, 20.0))
    action = -torch.ones(1, 4, dtype=F64)
    for k in range(1, 51):
        state = quad.step(state, action)
        t = k * quad.config.ctrl_dt
        assert float(quad.model.thrust(state.rotor).abs().max()) < 1e-12
        assert float(state.pos[0, 2]) == pytest.approx(20.0 - GRAVITY * t * t / 2, abs=1e-9)
        assert float(state.vel[0, 2]) == pytest.approx(-GRAVITY * t, abs=1e-9)
    assert torch.allclose(state.pos[0, :2], torch.tensor([0.5, -0.3], dtype=F64), atol=1e-12)
    assert torch.allclose(state.quat[0], torch.tensor([1.0, 0, 0, 0], dtype=F64), atol=1e-12)


def test_falling_with_drag_reaches_the_terminal_velocity_of_the_drag_model():
    af = load_airframe("visfly")
    quad = _quad("srt", motor_lag=False, ground=False, ctrl_dt=0.05, sim_dt=0.05)
    state = quad.initial_state(pos=_at(0.0, 0.0, 1000.0))
    for _ in range(400):                                   # 20 s, about 9 time constants
        state = quad.step(state, -torch.ones(1, 4, dtype=F64))
    k_lin = af.drag_linear[2]
    k_quad = 0.5 * af.air_density * af.drag_area[2]
    # k_quad v^2 + k_lin v = m g
    v_terminal = (-k_lin + math.sqrt(k_lin**2 + 4 * k_quad * af.mass * GRAVITY)) / (2 * k_quad)
    assert float(-state.vel[0, 2]) == pytest.approx(v_terminal, rel=1e-3)


def _srt_step_for(quad: Quadrotor, delta: tuple[float, float, float, float]) -> torch.Tensor:
    return (quad.hover_action() + torch.tensor(delta, dtype=F64))[None]


def test_positive_yaw_torque_spins_counter_clockwise_seen_from_above():
    quad = _quad("srt", ground=False)
    state = quad.initial_state(pos=_at(0.0, 0.0, 5.0))
    action = _srt_step_for(quad, (-0.1, -0.1, 0.1, 0.1))     # CW rotors 2, 3 up: +kappa T yaw torque
    for _ in range(10):
        state = quad.step(state, action)
    roll, pitch, yaw = euler_from_quat(state.quat)[0].tolist()
    assert float(state.omega[0, 2]) > 0.1 and yaw > 0.01
    assert abs(roll) < 1e-9 and abs(pitch) < 1e-9
    assert float(state.omega[0, :2].abs().max()) < 1e-9


def test_left_rotors_up_roll_right_way_and_front_rotors_up_pitch_nose_up():
    quad = _quad("srt", ground=False)
    left_up = _srt_step_for(quad, (-0.05, 0.05, 0.05, -0.05))   # rotors 1, 2 are on the left (+y)
    front_up = _srt_step_for(quad, (0.05, -0.05, 0.05, -0.05))  # rotors 0, 2 are in front (+x)
    for action, axis, sign in ((left_up, 0, 1.0), (front_up, 1, -1.0)):
        state = quad.initial_state(pos=_at(0.0, 0.0, 5.0))
        for _ in range(3):
            state = quad.step(state, action)
        assert sign * float(state.omega[0, axis]) > 0.05
        assert float(euler_from_quat(state.quat)[0, axis]) * sign > 0


def test_ground_contact_is_reported_and_the_reaction_stops_sinking():
    quad = _quad("srt", n=2)
    state = quad.initial_state(pos=torch.tensor([[0.0, 0.0, 0.3], [0.0, 0.0, 3.0]], dtype=F64))
    assert not bool(state.ground_contact.any())
    action = torch.stack((-torch.ones(4, dtype=F64), quad.hover_action()))
    contact_seen = []
    for _ in range(50):
        state = quad.step(state, action)
        contact_seen.append(bool(state.ground_contact[0]))
        assert float(state.pos[0, 2]) >= 0.0
    assert contact_seen[-1] and not contact_seen[0]
    assert float(state.pos[0, 2]) == 0.0 and float(state.vel[0, 2]) == 0.0
    assert not bool(state.ground_contact[1])

    no_ground = _quad("srt", ground=False)
    state = no_ground.initial_state(pos=_at(0.0, 0.0, 0.3))
    for _ in range(50):
        state = no_ground.step(state, -torch.ones(1, 4, dtype=F64))
    assert float(state.pos[0, 2]) < -1.0 and bool(state.ground_contact[0])


def test_wind_drags_along_the_air_relative_velocity():
    wind = torch.tensor([[4.0, 0.0, 0.0], [0.0, -3.0, 0.0], [2.0, 1.0, 0.0]], dtype=F64)
    quad = _quad("srt", n=3, wind=wind, motor_lag=False)
    vel = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [2.0, 1.0, 0.0]], dtype=F64)
    state = quad.initial_state(pos=_at(0.0, 0.0, 5.0, n=3), vel=vel)
    action = quad.hover_action().expand(3, 4)
    state = quad.step(state, action)
    af = quad.airframe
    dv = state.vel - vel
    # Agent 0: still air relative speed 4 along +x: a = (k_lin v + k_quad v^2) / m.
    expected = (af.drag_linear[0] * 4 + 0.5 * af.air_density * af.drag_area[0] * 16) / af.mass
    assert float(dv[0, 0]) / quad.config.ctrl_dt == pytest.approx(expected, rel=0.05)
    assert float(dv[1, 1]) < 0 and abs(float(dv[1, 0])) < 1e-12
    assert float(dv.abs()[2].max()) < 1e-12                    # moving with the air: no drag

    shared = _quad("srt", n=3, wind=(4.0, 0.0, 0.0), motor_lag=False)
    state = shared.step(shared.initial_state(pos=_at(0.0, 0.0, 5.0, n=3)), action)
    assert torch.allclose(state.vel[:, 0], torch.full((3,), float(dv[0, 0]), dtype=F64))


def test_action_delay_shifts_the_response_by_whole_control_steps():
    plain = _quad("ctbr")
    delayed = _quad("ctbr", action_delay_s=3 * plain.config.ctrl_dt)
    assert delayed.initial_state().action_queue.shape == (1, 3, 4)
    step_cmd = torch.tensor([[0.0, 0.5, 0.0, 0.0]], dtype=F64)
    hover = plain.hover_action()[None]
    a, b = plain.initial_state(pos=_at(0, 0, 2)), delayed.initial_state(pos=_at(0, 0, 2))
    trace_plain, trace_delayed = [], []
    for k in range(10):
        a = plain.step(a, step_cmd if k < 7 else hover)
        b = delayed.step(b, step_cmd if k < 7 else hover)
        trace_plain.append(a.omega[0, 0])
        trace_delayed.append(b.omega[0, 0])
    assert all(abs(float(x)) < 1e-12 for x in trace_delayed[:3])
    assert torch.allclose(torch.stack(trace_delayed[3:]), torch.stack(trace_plain[:7]), atol=1e-12)


def _manoeuvre(integrator: str, substeps: int, ctrl_dt: float = 0.04, duration: float = 1.0) -> torch.Tensor:
    """A smooth open-loop flight (SRT, sinusoidal thrusts, moving and turning), final state."""
    quad = _quad("srt", ctrl_dt=ctrl_dt, sim_dt=ctrl_dt / substeps, integrator=integrator, ground=False)
    state = quad.initial_state(pos=_at(0.0, 0.0, 5.0), vel=_at(3.0, 2.0, 1.0), omega=_at(0.3, -0.2, 0.1))
    hover = quad.hover_action()
    for i in range(round(duration / ctrl_dt)):
        t = i * ctrl_dt
        wobble = torch.tensor([math.sin(3 * t), math.cos(2 * t), -math.sin(2.5 * t), -math.cos(3 * t)], dtype=F64)
        state = quad.step(state, (hover + 0.05 * wobble)[None])
        assert float((state.quat.norm(dim=1) - 1).abs().max()) < 1e-12
    return torch.cat((state.pos, state.vel, state.quat, state.omega, state.rotor / 100), dim=1)


@pytest.fixture(scope="module")
def reference_manoeuvre() -> torch.Tensor:
    return _manoeuvre("rk4", 64)


@pytest.mark.parametrize("integrator, order", [("rk4", 4), ("euler", 1)])
def test_integrator_converges_at_its_order(integrator, order, reference_manoeuvre):
    reference = reference_manoeuvre
    errors = [float((_manoeuvre(integrator, k) - reference).abs().max()) for k in (4, 8, 16)]
    ratios = [errors[i] / errors[i + 1] for i in range(2)]
    expected = 2.0**order
    for r in ratios:
        assert expected * 0.75 < r < expected * 1.4, f"{integrator} error ratios {ratios}, expected ~{expected}"


def test_quaternions_stay_unit_in_float32_under_aggressive_rates():
    quad = _quad("ctbr", n=16, dtype=torch.float32, ground=False)
    state = quad.initial_state(pos=_at(0.0, 0.0, 50.0, n=16, dtype=torch.float32))
    gen = torch.Generator().manual_seed(0)
    for _ in range(200):
        action = torch.rand(16, 4, generator=gen) * 2 - 1
        state = quad.step(state, action)
    assert float((state.quat.norm(dim=1) - 1).abs().max()) < 1e-6


def test_where_selects_agents_and_detach_cuts_the_graph():
    quad = _quad("ctbr", n=3)
    a = quad.initial_state(pos=_at(0.0, 0.0, 1.0, n=3))
    b = quad.initial_state(pos=_at(5.0, 5.0, 5.0, n=3))
    mixed = QuadState.where(torch.tensor([True, False, True]), a, b)
    assert mixed.pos[:, 0].tolist() == [0.0, 5.0, 0.0]
    assert mixed.action_queue.shape == a.action_queue.shape
    action = quad.hover_action().expand(3, 4).clone().requires_grad_()
    stepped = quad.step(a, action)
    assert stepped.pos.requires_grad and not stepped.detach().pos.requires_grad
    assert stepped.pose().shape == (3, 7)


def test_put_rows_of_a_few_initial_states_matches_where_over_all_agents():
    """A reset puts the start states of the reset agents only: the same as ``where`` over all N,
    field for field, and gradients still flow through the rows kept."""
    quad = _quad("ctbr", n=4)
    gen = torch.Generator().manual_seed(3)
    state = quad.initial_state(pos=torch.rand(4, 3, generator=gen, dtype=quad.dtype) + 1.0)
    action = (torch.rand(4, 4, generator=gen, dtype=quad.dtype) * 2 - 1).requires_grad_()
    state = quad.step(state, action)
    starts = torch.rand(4, 3, generator=gen, dtype=quad.dtype) * 5.0
    idx = torch.tensor([0, 2])
    mask = torch.zeros(4, dtype=torch.bool).index_fill(0, idx, True)
    put = state.put_rows(idx, quad.initial_state(starts[idx], agents=2))
    where = QuadState.where(mask, quad.initial_state(starts), state)
    for f in dataclasses.fields(QuadState):
        assert torch.equal(getattr(put, f.name), getattr(where, f.name)), f.name
    put.pos.sum().backward()
    assert action.grad is not None and action.grad[[1, 3]].abs().sum() > 0 and not action.grad[[0, 2]].any()


@pytest.mark.parametrize("controller", ["ctbr", "ps"])
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_restart_matches_put_rows_of_initial_states_and_keeps_gradients(controller, dtype):
    """``restart`` (a reset's one operation per component) gives what putting ``initial_state``
    rows gives, bit for bit, with an action delay queue too; gradients still flow through the rows kept."""
    quad = _quad(controller, n=5, dtype=dtype, action_delay_s=0.06)
    assert quad.config.delay_steps > 0
    gen = torch.Generator().manual_seed(4)
    state = quad.initial_state(pos=torch.rand(5, 3, generator=gen, dtype=dtype) + 1.0)
    action = (torch.rand(5, 4, generator=gen, dtype=dtype) * 2 - 1).requires_grad_()
    for _ in range(3):
        state = quad.step(state, action)
    idx, starts = torch.tensor([3, 0]), torch.rand(2, 3, generator=gen, dtype=torch.float32) * 5.0 - 1.0
    put, restarted = state.put_rows(idx, quad.initial_state(starts, agents=2)), quad.restart(state, idx, starts)
    for f in dataclasses.fields(QuadState):
        a, b = getattr(put, f.name), getattr(restarted, f.name)
        assert a.dtype == b.dtype and torch.equal(a, b), f.name
    restarted.pos.sum().backward()
    assert action.grad is not None and action.grad[[1, 2, 4]].abs().sum() > 0 and not action.grad[[0, 3]].any()
