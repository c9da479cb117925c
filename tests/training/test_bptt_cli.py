"""``visfly-dist train --algo bptt|shac`` as a user runs it (subprocesses, tiny budgets), evaluating
the result from Python, and a worker killed mid-window."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from stable_baselines3.common.vec_env import VecMonitor

from visfly_dist.aggregator import PoolConfig
from visfly_dist.tasks import make_env
from visfly_dist.training.bptt import first_observation, load_actor
from visfly_dist.training.diff_common import DiffActor, rollout_window
from visfly_dist.training.evaluation import evaluate

CLI = [sys.executable, "-m", "visfly_dist.cli"]
TINY = ["--num-envs", "4", "--workers", "1", "--horizon", "8", "--lr", "1e-3", "--batch-size", "16",
        "--set", "max_episode_steps=12"]


def run_cli(*args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize("algo", ["bptt", "shac"])
def test_train_writes_config_checkpoints_logs_and_curve(algo: str, tmp_path: Path) -> None:
    out = tmp_path / algo
    proc = run_cli("train", "hover", "--algo", algo, "--timesteps", "256", "--checkpoint-every", "128",
                   "--out", str(out), *TINY)
    assert proc.returncode == 0, proc.stderr
    assert f'"algo": "{algo}"' in proc.stdout and '"horizon": 8' in proc.stdout
    assert sorted(p.name for p in (out / "checkpoints").glob("*.npz")) == ["step_128.npz", "step_256.npz"]
    with np.load(out / "final.npz", allow_pickle=False) as data:
        prefixes = {k.split("/")[0] for k in data.files}
    assert prefixes == ({"actor", "critic"} if algo == "shac" else {"actor"})
    with (out / "success_curve.csv").open() as f:
        rows = list(csv.DictReader(f))
    # 4 agents x 8-step windows = 32 steps per update; 12-step episodes end from the second window on.
    assert [int(r["timesteps"]) for r in rows] == list(range(64, 257, 32))
    assert all(float(r["mean_length"]) <= 12 for r in rows)
    with (out / "progress.csv").open() as f:
        progress = list(csv.DictReader(f))
    assert len(progress) == 8 and all(np.isfinite(float(r["losses/actor_loss"])) for r in progress)
    if algo == "shac":
        assert all(np.isfinite(float(r["losses/critic_loss"])) for r in progress)
    assert list(out.glob("events.out.tfevents.*")) and (out / "success_curve.png").stat().st_size > 1000

    proc = run_cli("eval", "hover", "--checkpoint", str(out / "final.npz"), "--episodes", "2", "--num-envs", "2",
                   "--workers", "1", "--json", str(out / "eval.json"))
    assert proc.returncode == 0, proc.stderr
    assert "deterministic: success" in proc.stdout and "sampled" not in proc.stdout
    assert '"deterministic"' in (out / "eval.json").read_text()
    proc = run_cli("eval", "hover", "--checkpoint", str(out / "final.npz"), "--mode", "sampled")
    assert proc.returncode != 0 and "deterministic" in proc.stderr and "Traceback" not in proc.stderr

    env = VecMonitor(make_env("hover", num_envs=2, seed=1, max_episode_steps=12, pool=PoolConfig(num_local_workers=1)))
    try:
        stats = evaluate(load_actor(out / "final.npz", env), env, episodes=2)
    finally:
        env.close()
    assert stats.episodes == 2 and 1 <= stats.mean_length <= 12


def test_a_worker_killed_mid_window_truncates_it_and_training_goes_on() -> None:
    env = make_env("hover", num_envs=4, requires_grad=True, seed=0, agents_per_scene=2,
                   pool=PoolConfig(num_local_workers=2, respawn=False))
    try:
        actor = DiffActor(env.observation_space)
        obs = first_observation(env)

        class KillAtThirdStep:
            """Forwards to the env; kills one worker process before the third step."""

            num_envs = env.num_envs
            calls = 0

            def step_tensor(self, action):
                if self.calls == 2:
                    worker = env.aggregator.workers[0]
                    os.kill(env.aggregator.local_worker_pids()[worker], signal.SIGKILL)
                self.calls += 1
                return env.step_tensor(action)

        window = rollout_window(KillAtThirdStep(), actor, obs, 8, 0.99)
        assert window.steps == 3 and window.lost_agents == 2
        window.loss.backward()
        assert all(torch.isfinite(p.grad).all() for p in actor.parameters() if p.grad is not None)
        env.detach()
        obs = {k: v.detach() for k, v in window.next_obs.items()}
        for _ in range(60):  # the lost scene is placed on the survivor in the background: a few short windows
            again = rollout_window(env, actor, obs, 8, 0.99)
            env.detach()
            obs = {k: v.detach() for k, v in again.next_obs.items()}
            if again.lost_agents == 0:
                break
        assert again.steps == 8 and again.lost_agents == 0
    finally:
        env.close()


def test_bad_algo_and_horizon_are_reported_together() -> None:
    from visfly_dist.errors import ConfigError
    from visfly_dist.training.config import TrainConfig

    with pytest.raises(ConfigError, match=r"algo='sac' must be one of .*horizon=0 must be an int >= 1"):
        TrainConfig(task="hover", algo="sac", horizon=0).resolved().validate()
