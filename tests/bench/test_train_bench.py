"""``visfly-dist bench train`` with tiny budgets: real training loop, real workers, well-formed rows."""

from __future__ import annotations

import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from visfly_dist.bench.train import CpuMonitor, CpuSnapshot, bench_train, busy_shares, process_cpu_s, worker_children
from visfly_dist.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]
TINY = {"num_envs": 2, "n_steps": 8, "batch_size": 8, "n_epochs": 1}


def check_row(row: dict, timesteps: int) -> None:
    assert row["timesteps"] >= timesteps and row["timing"] in ("sb3 wrapped", "trainer summary")
    assert row["env_steps_per_s"] > 0 and row["rollout_env_steps_per_s"] >= row["env_steps_per_s"]
    assert 0 < row["rollout_s"] <= row["loop_s"] and 0 < row["update_s"] <= row["loop_s"]
    assert row["learner_busy"] > 0
    # start-up (env, workers, scenes, model) ends where training begins; the final save and shut-down are apart
    assert row["startup_s"] > 0.5 and row["teardown_s"] > 0
    # the learner's figure is its collecting thread's part and the other threads' (Zenoh's) part
    assert row["learner_cpu_main_s_per_1k"] > 0 and row["learner_cpu_threads_s_per_1k"] > -1e-3
    assert row["learner_cpu_main_s_per_1k"] + row["learner_cpu_threads_s_per_1k"] == pytest.approx(
        row["learner_cpu_s_per_1k"], abs=2e-4)
    # Every rollout step renders on the workers, so they did some work, and no more than all the time.
    assert row["worker_processes"] == row["workers"] and 0 < row["workers_busy"] <= 1.05


def test_bench_train_tiny_local_run():
    out = bench_train("navigation", timesteps=32, workers=1, changes=TINY)
    (row,) = out["rows"]
    assert row["delay_ms"] is None and row["workers"] == 1
    check_row(row, 32)
    assert out["ratios"] == []
    assert worker_children() == []  # the run's workers are gone


def test_bench_train_delays_give_ratios_to_the_undelayed_run():
    out = bench_train("navigation", timesteps=16, delays=[0, 20], workers=1, changes=TINY)
    base, delayed = out["rows"]
    assert (base["delay_ms"], delayed["delay_ms"]) == (0, 20)
    for row in out["rows"]:
        check_row(row, 16)
    ratios = {r["ratio"]: r for r in out["ratios"]}
    whole = ratios[f"{base['algo']} delay 20 / 0 ms env_steps_per_s"]
    assert whole["value"] == pytest.approx(delayed["env_steps_per_s"] / base["env_steps_per_s"], rel=1e-2)
    assert whole["goal"] == ">= 0.9"


def test_busy_shares_from_snapshots():
    start = CpuSnapshot(wall=10.0, learner_cpu=1.0, workers={11: 2.0, 12: 0.5})
    end = CpuSnapshot(wall=12.0, learner_cpu=2.0, workers={11: 3.0, 12: 1.5})
    assert busy_shares(start, end) == {"learner_busy": 0.5, "workers_busy": 0.5, "worker_processes": 2}


def test_the_monitors_own_sampling_is_not_the_learners_cpu():
    """The sampler scans /proc in the training process; the learner's figure leaves its CPU out:
    with the main thread asleep, the learner's CPU barely moves while the process's grows."""
    monitor = CpuMonitor(period_s=0.0)  # scan back to back: as busy as the sampler can be
    try:
        learner0, process0 = monitor.learner_cpu_s(), time.process_time()
        time.sleep(1.0)
        learner1, process1 = monitor.learner_cpu_s(), time.process_time()
    finally:
        monitor.close()
    assert process1 - process0 > 0.1  # the sampler worked
    assert learner1 - learner0 < 0.05 * (process1 - process0)


def test_process_cpu_of_this_process_and_of_a_missing_one():
    spin = sum(i * i for i in range(300_000))
    assert spin and process_cpu_s(os.getpid()) > 0
    assert process_cpu_s(2 ** 22 + 7) is None


def test_worker_children_finds_workers_started_through_a_launcher():
    """A process whose argv reads like a worker, started by an intermediate shell, is found; the
    shell itself is not."""
    fake_worker = f"{shlex.quote(sys.executable)} -c 'import time; time.sleep(60)' visfly_dist.cli worker"
    launcher = subprocess.Popen(["sh", "-c", f"{fake_worker}; true"])
    try:
        deadline = time.monotonic() + 20
        while not (found := worker_children()) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(found) == 1 and found[0] != launcher.pid
        assert process_cpu_s(found[0]) is not None
    finally:
        for pid in worker_children():
            os.kill(pid, signal.SIGTERM)
        launcher.wait(20)


def test_bench_train_rejects_bad_budget():
    with pytest.raises(ConfigError, match="timesteps=0 must be an int >= 1"):
        bench_train(timesteps=0)
    with pytest.raises(ConfigError, match="n_epochs=0 must be an int >= 1"):  # the trainer's own check, unwrapped
        bench_train(timesteps=8, workers=1, changes={"n_epochs": 0})


def test_bench_train_cli_is_registered():
    proc = subprocess.run([sys.executable, "-m", "visfly_dist.cli", "bench", "train", "--help"], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and "--delay-ms" in proc.stdout and "--timesteps" in proc.stdout


def test_trainer_ratios_pair_each_tensor_run_with_the_nearest_sb3_run() -> None:
    from visfly_dist.bench.train import trainer_ratios

    def row(algo: str, value: float) -> dict:
        return dict(algo=algo, delay_ms=None, env_steps_per_s=value, rollout_env_steps_per_s=value, learner_cpu_s_per_1k=value)

    rows = [row("sb3-ppo", 1.0), row("ppo", 2.0), row("ppo", 6.0), row("sb3-ppo", 3.0)]   # A B B A
    ratios = [r["value"] for r in trainer_ratios(rows) if r["ratio"] == "ppo / sb3-ppo env_steps_per_s"]
    assert ratios == [2.0, 2.0]          # each ppo run against the sb3 run beside it, not the first one
    assert trainer_ratios([row("ppo", 1.0)]) == []
