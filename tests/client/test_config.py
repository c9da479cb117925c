"""EnvConfig.validate: every problem reported at once, before any process starts."""

import dataclasses

import pytest
import torch

from visfly_dist.aggregator import PoolConfig
from visfly_dist.client.config import EnvConfig
from visfly_dist.dynamics import DynamicsConfig, Quadrotor, load_airframe
from visfly_dist.client.noise import NoiseSpec
from visfly_dist.errors import ConfigError
from visfly_dist.protocol.cameras import CameraSpec


def test_defaults_are_valid():
    cfg = EnvConfig()
    assert cfg.validate() is cfg and cfg.num_scenes == 16 and cfg.controller == "ctbr"


def test_env_and_dynamics_agree_on_the_control_step():
    """One env step is one control step of the dynamics: same default, and a drone coasting at 1 m/s
    (hover thrust, no ground, no lag) moves ``ctrl_dt`` metres in one step of the env's dynamics."""
    cfg = EnvConfig()
    assert cfg.ctrl_dt == DynamicsConfig().ctrl_dt and cfg.sim_dt == DynamicsConfig().sim_dt
    dyn = cfg.replace(ground=False, motor_lag=False).dynamics_config()
    assert dyn.ctrl_dt == cfg.ctrl_dt and dyn.substeps * dyn.sim_dt == pytest.approx(cfg.ctrl_dt)
    quad = Quadrotor(dyn, load_airframe(cfg.airframe), num_agents=1, dtype=torch.float64)
    state = quad.initial_state(pos=torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64),
                               vel=torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64))
    moved = float(quad.step(state, quad.hover_action()[None]).pos[0, 0])
    assert moved == pytest.approx(cfg.ctrl_dt * 1.0, rel=1e-3)  # drag slows it by ~1e-4 relative


def test_every_shared_dynamics_setting_reaches_the_dynamics_config():
    """Every EnvConfig field named as a DynamicsConfig field is passed on (a dropped one fails here), and
    the env has every DynamicsConfig setting except those it deliberately leaves at their defaults."""
    shared = set(EnvConfig.dynamics_field_names())
    left_out = {f.name for f in dataclasses.fields(DynamicsConfig)} - shared
    assert left_out == {"position_origin", "check_actions", "adjoint"}, left_out
    changed = dict(controller="srt", sim_dt=0.01, ctrl_dt=0.04, integrator="euler", motor_lag=False,
                   action_delay_s=0.04, wind=(1.0, -2.0, 0.5), ground=False, compile=True)
    assert set(changed) == shared
    defaults = DynamicsConfig()
    for name, value in changed.items():
        assert getattr(defaults, name) != value, name  # each value differs from the default
        assert getattr(EnvConfig(), name) == getattr(defaults, name), name  # and the defaults are the dynamics'
    dyn = EnvConfig(**changed).dynamics_config()
    for name, value in changed.items():
        assert getattr(dyn, name) == value, name


def test_divisibility_message_names_both_values():
    with pytest.raises(ConfigError, match=r"num_envs=5 must be divisible by agents_per_scene=2"):
        EnvConfig(num_envs=5, agents_per_scene=2).validate()


def test_every_problem_is_listed_at_once():
    cfg = EnvConfig(num_envs=0, controller="rpm", sim_dt=0.007, scenes=("gen:nowhere",), airframe="paper-plane",
                    cameras=(CameraSpec(name="a"), CameraSpec(name="a")), device="tpu:9",
                    noise={"state": [NoiseSpec("poisson", {})], "b": [NoiseSpec("gaussian", {"std": 1.0})]},
                    pool=PoolConfig(backend="vulkan"), drone_radius=-1.0)
    with pytest.raises(ConfigError) as info:
        cfg.validate()
    msg = str(info.value)
    for part in ("num_envs=0", "controller='rpm'", "sim_dt=0.007", "'nowhere'", "paper-plane",
                 "camera names ['a', 'a'] must be unique", "device='tpu:9'", "does not apply to a state",
                 "noise for unknown sensor 'b'", "backend='vulkan'", "drone_radius=-1.0"):
        assert part in msg, part


def test_replace_rejects_unknown_fields_by_name():
    with pytest.raises(ConfigError, match=r"unknown EnvConfig settings \['speed'\]"):
        EnvConfig().replace(speed=3)
    assert EnvConfig().replace(num_envs=4).num_envs == 4
