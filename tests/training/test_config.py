"""Training configuration: overrides from the command line, validation, and what reaches make_env."""

from __future__ import annotations

import argparse

import pytest

from visfly_dist.aggregator.config import PoolConfig
from visfly_dist.errors import ConfigError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.training.config import TASK_DEFAULTS, TrainConfig, parse_override
from visfly_dist.training.ppo import env_kwargs
from visfly_dist.training.train_cli import add_arguments, config_from_args


def test_parse_override_reads_json_else_text() -> None:
    assert parse_override("max_episode_steps=64") == ("max_episode_steps", 64)
    assert parse_override("scenes=[\"gen:pillars\"]") == ("scenes", ["gen:pillars"])
    assert parse_override("controller=lv") == ("controller", "lv")
    with pytest.raises(ConfigError, match="'oops' must look like KEY=VALUE"):
        parse_override("oops")


def test_resolved_fills_task_defaults_and_validate_lists_every_problem() -> None:
    cfg = TrainConfig(task="navigation", num_envs=4).resolved()
    assert cfg.num_envs == 4 and cfg.timesteps == TASK_DEFAULTS["navigation"]["timesteps"]
    assert cfg.out.startswith("runs/navigation-")
    assert cfg.log_std_init == -1.0 and TrainConfig(task="hover").resolved().log_std_init == 0.0
    assert TrainConfig(task="navigation", log_std_init=-0.5).resolved().log_std_init == -0.5
    bad = TrainConfig(task="hover", num_envs=2, n_steps=8, batch_size=64, lr=2.0, backbone="vgg", log_std_init=9.0).resolved()
    with pytest.raises(ConfigError) as err:
        bad.validate()
    message = str(err.value)
    assert "batch_size=64 must be <= n_steps * num_envs = 16" in message
    assert "lr=2.0" in message and "backbone='vgg'" in message and "log_std_init=9.0 must be a number in [-5, 2]" in message
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg


def test_env_kwargs_map_flags_onto_the_task_pool_and_cameras() -> None:
    cfg = TrainConfig(task="navigation", workers=1, connect=("tcp/127.0.0.1:7447",), run_id="exp1", seed=5,
                      overrides={"cameras": [{"name": "depth", "width": 32, "height": 32}], "pool": {"lease_ms": 5000}})
    kwargs = env_kwargs(cfg)
    assert kwargs["seed"] == 5
    assert kwargs["cameras"] == (CameraSpec(name="depth", width=32, height=32),)
    pool = kwargs["pool"]
    assert isinstance(pool, PoolConfig)
    assert (pool.num_local_workers, pool.connect, pool.run_id, pool.lease_ms) == (1, ("tcp/127.0.0.1:7447",), "exp1", 5000)
    assert "pool" not in env_kwargs(TrainConfig(task="hover"))  # the task's own pool stays untouched
    with pytest.raises(ConfigError, match="unknown task 'hovr'"):
        env_kwargs(TrainConfig(task="hovr", workers=1))


def test_landing_trains_with_bptt_by_default_and_with_ppo_defaults_under_algo_ppo():
    landing = TrainConfig(task="landing").resolved()
    assert (landing.algo, landing.num_envs, landing.horizon, landing.lr, landing.timesteps) == ("bptt", 8, 16, 3e-3, 100_000)
    ppo = TrainConfig(task="landing", algo="ppo").resolved()
    assert (ppo.algo, ppo.num_envs, ppo.lr, ppo.timesteps) == ("ppo", 16, 3e-4, 300_000)
    assert TrainConfig(task="landing", lr=1e-3).resolved().lr == 1e-3  # given values win
    hover = TrainConfig(task="hover", algo="bptt").resolved()
    assert (hover.algo, hover.horizon, hover.lr, hover.num_envs) == ("bptt", 32, 3e-4, 16)
    assert TrainConfig(task="navigation").resolved().algo == "ppo"          # the tensor PPO, measured there
    assert TrainConfig(task="hover").resolved().algo == "ppo"               # measured there too
    assert TrainConfig(task="racing").resolved().algo == "sb3-ppo"          # not yet measured with it
    assert TrainConfig(task="landing", algo="shac").resolved().num_envs == 8  # the gradient row applies to shac too


def test_overlap_is_on_by_default_only_when_every_worker_is_remote():
    assert TrainConfig(task="navigation").resolved().overlap is False            # local workers need the cores
    assert TrainConfig(task="navigation", workers=2).resolved().overlap is False
    assert TrainConfig(task="navigation", workers=0, connect=("tcp/10.0.0.2:7447",)).resolved().overlap is True
    assert TrainConfig(task="navigation", workers=0, overlap=False).resolved().overlap is False  # given values win
    assert TrainConfig(task="navigation", overlap=True).resolved().overlap is True
    assert TrainConfig(task="landing", workers=0).resolved().overlap is False    # BPTT has no PPO update to overlap


def test_overlap_flags_reach_the_config():
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    for flags, expected in ([], None), (["--overlap"], True), (["--no-overlap"], False):
        assert config_from_args(parser.parse_args(["navigation", *flags])).overlap is expected
