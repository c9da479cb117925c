"""Bad configuration fails early with a ConfigError that names the problem."""

from __future__ import annotations

import json
import warnings

import pytest
import torch

from visfly_dist.dynamics import Distribution, DynamicsConfig, InitialStateSampler, Quadrotor, load_airframe
from visfly_dist.errors import ConfigError


@pytest.mark.parametrize("kwargs, match", [
    (dict(controller="mpc"), r"unknown controller='mpc'.*'srt', 'ctbr', 'lv', 'ps'"),
    (dict(integrator="rk2"), r"unknown integrator='rk2'"),
    (dict(sim_dt=0.003, ctrl_dt=0.02), r"sim_dt=0.003 must divide ctrl_dt=0.02"),
    (dict(sim_dt=0.0), r"must be > 0"),
    (dict(action_delay_s=0.05, ctrl_dt=0.02), r"action_delay_s=0.05 must be a non-negative multiple of ctrl_dt=0.02"),
    (dict(wind=(1.0, 2.0)), r"wind of shape \(2,\)"),
    (dict(wind=(1.0, float("nan"), 0.0)), r"wind must be finite"),
])
def test_invalid_config_is_rejected_at_construction(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        DynamicsConfig(**kwargs)


def test_every_problem_is_reported_at_once():
    with pytest.raises(ConfigError, match=r"controller='x'.*integrator='y'"):
        DynamicsConfig(controller="x", integrator="y")


def test_quadrotor_arguments_are_checked():
    with pytest.raises(ConfigError, match=r"unknown airframe 'crazyflie'.*visfly"):
        Quadrotor(DynamicsConfig(), "crazyflie")
    with pytest.raises(ConfigError, match=r"num_agents=0 must be an int >= 1"):
        Quadrotor(DynamicsConfig(), num_agents=0)
    with pytest.raises(ConfigError, match=r"dtype=torch.float16"):
        Quadrotor(DynamicsConfig(), dtype=torch.float16)
    with pytest.raises(ConfigError, match=r"wind of shape \(2, 3\) must be \(3,\) or \(3, 3\)"):
        Quadrotor(DynamicsConfig(wind=torch.zeros(2, 3)), num_agents=3)
    quad = Quadrotor(DynamicsConfig(), num_agents=3)
    with pytest.raises(ConfigError, match=r"pos has shape \(2, 3\); expected \(3, 3\)"):
        quad.initial_state(pos=torch.zeros(2, 3))


def test_bad_actions_are_rejected_in_step():
    quad = Quadrotor(DynamicsConfig(), num_agents=3)
    state = quad.initial_state()
    with pytest.raises(ConfigError, match=r"action of shape \(3, 3\) must be a tensor of shape \(3, 4\)"):
        quad.step(state, torch.zeros(3, 3))
    with pytest.raises(ConfigError, match=r"action of shape list"):
        quad.step(state, [[0.0] * 4] * 3)
    bad = torch.zeros(3, 4)
    bad[1, 2] = float("nan")
    with pytest.raises(ConfigError, match=r"NaN or infinite entries \(agents \[1\]"):
        quad.step(state, bad)
    unchecked = Quadrotor(DynamicsConfig(check_actions=False), num_agents=3)
    assert bool(torch.isnan(unchecked.step(state, bad).pos).any())     # the caller opted out


def test_checking_actions_that_need_gradients_warns_of_nothing():
    """BPTT's actions require grad: the finiteness check reads them without a torch warning."""
    quad = Quadrotor(DynamicsConfig(), num_agents=2)
    action = torch.zeros(2, 4, requires_grad=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        state = quad.step(quad.initial_state(), action)
    state.pos.sum().backward()
    assert action.grad is not None and torch.isfinite(action.grad).all()


def test_airframe_files_are_validated(tmp_path):
    data = json.loads((load_airframe.__globals__["AIRFRAME_DIR"] / "visfly.json").read_text())
    missing = dict(data)
    del missing["mass"]
    (tmp_path / "missing.json").write_text(json.dumps(missing))
    with pytest.raises(ConfigError, match=r"missing fields \['mass'\]"):
        load_airframe(tmp_path / "missing.json")
    heavy = dict(data, mass=3.0)
    (tmp_path / "heavy.json").write_text(json.dumps(heavy))
    with pytest.raises(ConfigError, match=r"cannot lift mass=3.0 kg"):
        load_airframe(tmp_path / "heavy.json")
    negative = dict(data, inertia=[1e-3, -1e-3, 1e-3])
    (tmp_path / "negative.json").write_text(json.dumps(negative))
    with pytest.raises(ConfigError, match=r"inertia=.* must be > 0"):
        load_airframe(tmp_path / "negative.json")
    with pytest.raises(ConfigError, match=r"cannot read airframe file"):
        load_airframe(tmp_path / "absent.json")
    # the collision radius has one home, the env's drone_radius: an airframe file naming one is refused
    (tmp_path / "radius.json").write_text(json.dumps(dict(data, radius=0.25)))
    with pytest.raises(ConfigError, match=r"'radius' is not an airframe field.*drone_radius=0.25"):
        load_airframe(tmp_path / "radius.json")


def test_sampler_settings_are_validated():
    with pytest.raises(ConfigError, match=r"unknown kind='gamma'"):
        Distribution("gamma")
    with pytest.raises(ConfigError, match=r"must be >= 0"):
        Distribution("normal", b=(1.0, -1.0, 0.0))
    with pytest.raises(ConfigError, match=r"unknown orientation_mode='quat'"):
        InitialStateSampler(orientation_mode="quat")
