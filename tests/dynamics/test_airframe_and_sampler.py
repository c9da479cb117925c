"""Shipped airframes carry the reference numbers; the initial-state sampler is seeded and shaped."""

from __future__ import annotations

import math

import pytest
import torch

from visfly_dist.dynamics import (Distribution, DynamicsConfig, InitialStateSampler, Quadrotor, list_airframes,
                                  load_airframe)
from visfly_dist.dynamics.airframe import AIRFRAME_DIR
from visfly_dist.dynamics.rotations import euler_from_quat, quat_multiply, quat_to_rotmat


def test_shipped_airframes_and_the_visfly_numbers():
    assert {"visfly", "visfly-fast", "visfly-large"} <= set(list_airframes())
    af = load_airframe("visfly")
    assert (af.mass, tuple(af.inertia)) == (0.46, (1.01e-3, 1.53e-3, 2.03e-3))
    assert (af.arm_length, af.yaw_torque_coeff) == (0.075, 0.016)
    assert tuple(af.rotor_speed_range) == (200.0, 3500.0) and af.motor_time_constant == 0.033
    assert af.max_rotor_thrust == pytest.approx(5.0155, abs=1e-3)
    assert 4 * af.max_rotor_thrust / (af.mass * 9.81) == pytest.approx(4.44, abs=0.01)
    assert load_airframe("visfly-fast").max_body_rate == 3.0
    large = load_airframe(AIRFRAME_DIR / "visfly-large.json")
    assert (large.mass, large.arm_length, large.max_body_rate) == (0.73, 0.17, 6.0)


def test_same_generator_seed_gives_the_same_sample_and_others_differ():
    sampler = InitialStateSampler(pos=Distribution("normal", b=(1.0, 1.0, 1.0)),
                                  orientation=Distribution("uniform", b=(0.3, 0.3, math.pi)))
    a = sampler.sample(5, torch.Generator().manual_seed(7))
    b = sampler.sample(5, torch.Generator().manual_seed(7))
    c = sampler.sample(5, torch.Generator().manual_seed(8))
    assert torch.equal(a.pos, b.pos) and torch.equal(a.quat, b.quat)
    assert not torch.equal(a.pos, c.pos)


def test_distributions_have_the_stated_ranges_and_moments():
    g = torch.Generator().manual_seed(0)
    uniform = Distribution("uniform", a=(1.0, -2.0, 0.0), b=(0.5, 0.0, 2.0)).sample(20000, g, torch.float64)
    assert float(uniform[:, 0].min()) >= 0.5 and float(uniform[:, 0].max()) <= 1.5
    assert bool((uniform[:, 1] == -2.0).all())
    assert float(uniform[:, 2].std()) == pytest.approx(2.0 / math.sqrt(3), rel=0.03)
    normal = Distribution("normal", a=(0.0, 3.0, 0.0), b=(1.0, 0.5, 0.0)).sample(20000, g, torch.float64)
    assert float(normal[:, 1].mean()) == pytest.approx(3.0, abs=0.02)
    assert float(normal[:, 1].std()) == pytest.approx(0.5, rel=0.03)


def test_orientation_modes():
    g = torch.Generator().manual_seed(1)
    euler = InitialStateSampler(orientation=Distribution("uniform", b=(0.4, 0.3, 3.0)))
    s = euler.sample(1000, g, torch.float64)
    angles = euler_from_quat(s.quat)
    assert float(angles[:, 0].abs().max()) <= 0.4 + 1e-9 and float(angles[:, 1].abs().max()) <= 0.3 + 1e-9
    assert float(angles[:, 2].abs().max()) > 2.5
    small = InitialStateSampler(orientation=Distribution("normal", b=(0.1, 0.1, 0.1)), orientation_mode="small_angle")
    q = small.sample(1000, g, torch.float64).quat
    assert torch.allclose(q.norm(dim=1), torch.ones(1000, dtype=torch.float64))
    tilt = torch.acos(quat_to_rotmat(q)[:, 2, 2].clamp(-1, 1))
    assert float(tilt.mean()) == pytest.approx(0.1 * math.sqrt(math.pi / 2), rel=0.1)   # Rayleigh mean


def test_a_sample_becomes_a_state():
    quad = Quadrotor(DynamicsConfig(), num_agents=4)
    s = InitialStateSampler(vel=Distribution("uniform", b=(1.0, 1.0, 1.0))).sample(4, torch.Generator().manual_seed(0))
    state = quad.initial_state(pos=s.pos + torch.tensor([0.0, 0.0, 1.0]), vel=s.vel, quat=s.quat, omega=s.omega)
    assert torch.equal(state.vel, s.vel)
    assert quad.step(state, quad.hover_action().expand(4, 4)).pos.shape == (4, 3)


def test_quat_multiply_composes_rotations():
    g = torch.Generator().manual_seed(2)
    sampler = InitialStateSampler(orientation=Distribution("uniform", b=(1.0, 1.0, 3.0)))
    p, q = (sampler.sample(10, g, torch.float64).quat for _ in range(2))
    assert torch.allclose(quat_to_rotmat(quat_multiply(p, q)), quat_to_rotmat(p) @ quat_to_rotmat(q), atol=1e-12)
