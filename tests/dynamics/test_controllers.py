"""Closed-loop behaviour of the controllers: PS and LV step responses, CTBR body-rate tracking."""

from __future__ import annotations

import math

import pytest
import torch

from visfly_dist.dynamics import DynamicsConfig, Distribution, InitialStateSampler, Quadrotor
from visfly_dist.dynamics.rotations import euler_from_quat

F64 = torch.float64
AGENTS = 32
ORIGIN = (0.0, 0.0, 3.0)
SAMPLER = InitialStateSampler(
    pos=Distribution("uniform", b=(0.5, 0.5, 0.5)),
    vel=Distribution("uniform", b=(1.0, 1.0, 0.5)),
    orientation=Distribution("uniform", b=(0.4, 0.4, 0.8)),
    omega=Distribution("uniform", b=(1.0, 1.0, 1.0)),
)


def _fly_step(controller: str, action: tuple[float, ...], seconds: float, seed: int = 0):
    quad = Quadrotor(DynamicsConfig(controller=controller, position_origin=ORIGIN), num_agents=AGENTS, dtype=F64)
    x = SAMPLER.sample(AGENTS, torch.Generator().manual_seed(seed), F64)
    state = quad.initial_state(pos=x.pos + torch.tensor(ORIGIN, dtype=F64), vel=x.vel, quat=x.quat, omega=x.omega)
    act = torch.tensor(action, dtype=F64).expand(AGENTS, 4)
    states = [state]
    for _ in range(round(seconds / quad.config.ctrl_dt)):
        state = quad.step(state, act)
        states.append(state)
    return quad, states


def _metrics(values: torch.Tensor, target: torch.Tensor, tol: float, dt: float) -> tuple[float, float]:
    """Worst settling time (last time any agent is farther than ``tol`` from ``target``) and worst
    overshoot (how far past the target along the initial error, as a fraction of the step)."""
    err = values - target                                        # (T, N, 3)
    far = err.norm(dim=2) > tol
    settle = float((far.to(F64) * torch.arange(len(values), dtype=F64)[:, None]).max()) * dt
    direction = -err[0] / err[0].norm(dim=1, keepdim=True)
    past = (err * direction).sum(dim=2).max(dim=0).values.clamp_min(0)
    return settle, float((past / err[0].norm(dim=1)).max())


def test_position_step_settles_from_random_initial_states():
    """PS: a step to (1, -1, 0.5) m from the origin with yaw 0.6 rad, from 32 random initial states
    (position +-0.5 m, velocity +-1 m/s, roll/pitch +-0.4 rad, yaw +-0.8 rad, rates +-1 rad/s).

    Tuned for (visfly airframe, position P 1, velocity P 3, attitude P 70/70/25, D 13.5/13.5/9):
    worst settling within 5 cm in about 2.6 s, worst overshoot about 1 % of the step (asserted
    with margin: 3.2 s and 5 %); yaw within 0.01 rad at the end.
    """
    quad, states = _fly_step("ps", (0.1, -0.1, 0.05, 0.6 / math.pi), seconds=5.0)
    target = torch.tensor(ORIGIN, dtype=F64) + torch.tensor([1.0, -1.0, 0.5], dtype=F64)
    settle, overshoot = _metrics(torch.stack([s.pos for s in states]), target, 0.05, quad.config.ctrl_dt)
    print(f"PS settle {settle:.2f} s, overshoot {overshoot:.3f}")
    assert settle < 3.2 and overshoot < 0.05
    assert float((states[-1].pos - target).norm(dim=1).max()) < 5e-3
    yaw = euler_from_quat(states[-1].quat)[:, 2]
    assert float((yaw - 0.6).abs().max()) < 0.01


def test_velocity_step_settles_and_honours_yaw():
    """LV: a velocity step to (1.5, -1, 0.5) m/s with yaw 0.6 rad from the same random states.

    Tuned: worst settling within 0.05 m/s in about 1.2 s, worst overshoot about 15 % of the step
    (initial velocities and attitudes add to it) (asserted: 1.6 s and 25 %); the drag is fed
    forward, so the final velocity error is below 1e-3 m/s even at speed.
    """
    quad, states = _fly_step("lv", (0.15, -0.1, 0.05, 0.6 / math.pi), seconds=3.0)
    target = torch.tensor([1.5, -1.0, 0.5], dtype=F64)
    settle, overshoot = _metrics(torch.stack([s.vel for s in states]), target, 0.05, quad.config.ctrl_dt)
    print(f"LV settle {settle:.2f} s, overshoot {overshoot:.3f}")
    assert settle < 1.6 and overshoot < 0.25
    assert float((states[-1].vel - target).norm(dim=1).max()) < 1e-3
    yaw = euler_from_quat(states[-1].quat)[:, 2]
    assert float((yaw - 0.6).abs().max()) < 0.01


@pytest.mark.parametrize("yaw", [-3.0, 3.0])
def test_lv_yaw_command_turns_the_short_way_round_to_large_angles(yaw):
    quad, states = _fly_step("lv", (0.0, 0.0, 0.0, yaw / math.pi), seconds=4.0)
    final = euler_from_quat(states[-1].quat)[:, 2]
    assert float(torch.remainder(final - yaw + math.pi, 2 * math.pi).sub(math.pi).abs().max()) < 0.01


@pytest.mark.parametrize("motor_lag", [True, False])
def test_ctbr_tracks_a_body_rate_step_within_a_few_motor_time_constants(motor_lag):
    """CTBR from hover: roll-rate step to 0.75 * max rate with a pitch and yaw rate, collective at hover.
    With motor lag (tau 0.033 s) the rate is within 10 % after 4 tau and within 2 % after 8 tau."""
    quad = Quadrotor(DynamicsConfig(controller="ctbr", ctrl_dt=0.005, sim_dt=0.005, motor_lag=motor_lag),
                     num_agents=1, dtype=F64)
    tau = quad.airframe.motor_time_constant
    state = quad.initial_state(pos=torch.tensor([[0.0, 0.0, 5.0]], dtype=F64))
    action = torch.tensor([[quad.hover_action()[0].item(), 0.75, -0.5, 0.5]], dtype=F64)
    target = action[0, 1:] * quad.airframe.max_body_rate
    errors = []
    for _ in range(round(10 * tau / 0.005)):
        state = quad.step(state, action)
        errors.append(float((state.omega[0] - target).abs().max() / target.abs().max()))
    at = lambda t: max(errors[round(t / 0.005) - 1:])                  # noqa: E731 (worst error from t on)
    assert at(4 * tau) < 0.10 and at(8 * tau) < 0.02, errors[::4]
