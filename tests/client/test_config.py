"""EnvConfig.validate: every problem reported at once, before any process starts."""

import pytest

from visfly_dist.aggregator import PoolConfig
from visfly_dist.client.config import EnvConfig
from visfly_dist.client.noise import NoiseSpec
from visfly_dist.errors import ConfigError
from visfly_dist.protocol.cameras import CameraSpec


def test_defaults_are_valid():
    cfg = EnvConfig()
    assert cfg.validate() is cfg and cfg.num_scenes == 16 and cfg.controller == "ctbr" and cfg.ctrl_dt == 0.03


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
