"""``visfly-dist train`` and ``visfly-dist eval`` as a user runs them: subprocesses, tiny budgets."""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import imageio.v2 as imageio
import pytest
from PIL import Image

from tests.helpers import wait_for
from visfly_dist.training.evaluation import missing_normalization

CLI = [sys.executable, "-m", "visfly_dist.cli"]
TINY = ["--num-envs", "4", "--workers", "1", "--n-steps", "32", "--batch-size", "64", "--set", "max_episode_steps=20"]


def run_cli(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("runs") / "hover-tiny"
    proc = run_cli("train", "hover", "--timesteps", "512", "--checkpoint-every", "256", "--log-std-init", "-0.5",
                   "--out", str(out), *TINY)
    assert proc.returncode == 0, proc.stderr
    assert '"task": "hover"' in proc.stdout  # the full config is printed
    starting = next(line for line in proc.stdout.splitlines() if line.startswith("starting the env: "))
    assert "local worker(s)" in starting and re.search(r"^env ready in \d+\.\d s$", proc.stdout, re.M), proc.stdout
    return out


def test_train_writes_config_checkpoints_logs_and_curve(trained_run: Path) -> None:
    config = json.loads((trained_run / "config.json").read_text())
    assert config["task"] == "hover" and config["num_envs"] == 4 and config["overrides"] == {"max_episode_steps": 20}
    assert config["log_std_init"] == -0.5
    from stable_baselines3 import PPO

    log_std = PPO.load(trained_run / "final.zip", device="cpu").policy.log_std.detach()
    assert log_std.shape == (4,) and (log_std + 0.5).abs().max() < 0.1  # started at -0.5, not SB3's 0
    assert (trained_run / "final.zip").is_file() and (trained_run / "final.norm.npz").is_file()
    assert sorted(p.name for p in (trained_run / "checkpoints").glob("*.zip")) == ["step_256.zip", "step_512.zip"]
    assert list(trained_run.glob("events.out.tfevents.*"))
    with (trained_run / "success_curve.csv").open() as f:
        rows = list(csv.DictReader(f))
    # 20-step episodes: every rollout of 4 x 32 steps ends episodes, so each gets a row.
    assert [int(r["timesteps"]) for r in rows] == [128, 256, 384, 512]
    assert all(0.0 <= float(r["success_rate"]) <= 1.0 and float(r["mean_length"]) <= 20 for r in rows)
    assert (trained_run / "success_curve.png").stat().st_size > 1000
    # the local workers' logs stay with the run
    logs = sorted((trained_run / "workers").glob("*.log"))
    assert [p.name for p in logs] == ["local-0.log"] and "worker local-0 ready on run" in logs[0].read_text()


def test_eval_reports_both_modes_and_writes_a_gif_of_the_first_episode(trained_run: Path, tmp_path: Path) -> None:
    gif, report = tmp_path / "hover.gif", tmp_path / "eval.json"
    proc = run_cli("eval", "hover", "--checkpoint", str(trained_run / "final.zip"), "--episodes", "4", "--num-envs", "2",
                   "--workers", "1", "--video", str(gif), "--json", str(report))
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert "seed 12345 (training seed 0)" in lines[0]
    assert lines[1].strip().startswith("deterministic: success") and lines[2].strip().startswith("sampled: success")
    stats = json.loads(report.read_text())
    assert stats["seed"] == 12345 and stats["training_seed"] == 0 and set(stats["results"]) == {"deterministic", "sampled"}
    for mode, result in stats["results"].items():
        assert result["mode"] == mode and result["episodes"] == 4 and 1 <= result["mean_length"] <= 20
        lo, hi = result["success_ci95"]
        assert 0 <= lo <= result["success_rate"] <= hi <= 1
        assert sum(result["end_causes"].values()) == 4 and len(result["episode_log"]) == 4
        assert all(e["end_cause"] in result["end_causes"] and e["scene"].startswith("gen:empty?seed=")
                   for e in result["episode_log"])
        assert result["scenes"] == sorted({e["scene"] for e in result["episode_log"]})
    first = stats["results"]["deterministic"]
    frames = imageio.mimread(gif)
    # One frame per step of agent 0's first episode (the settings of the run: 20-step episodes).
    assert len(frames) == first["video_frames"] == first["video_episode_length"]
    assert 1 <= len(frames) <= 20 and frames[0].shape[:2] == (192, 192)
    assert Image.open(gif).info["duration"] == 30  # the env's 0.03 s step


@pytest.mark.parametrize("task", ["racing", "tracking"])
def test_tiny_training_of_the_other_state_tasks(task: str, tmp_path: Path) -> None:
    out = tmp_path / task
    extra = ["--set", "cameras=[]"] if task == "tracking" else []
    proc = run_cli("train", task, "--timesteps", "256", "--checkpoint-every", "0", "--out", str(out), *TINY, *extra)
    assert proc.returncode == 0, proc.stderr
    assert (out / "final.zip").is_file() and "done: 256 steps" in proc.stdout


def test_eval_refuses_the_training_seed(trained_run: Path) -> None:
    proc = run_cli("eval", "hover", "--checkpoint", str(trained_run / "final.zip"), "--seed", "0")
    assert proc.returncode == 2 and "--seed 0 is the training run's seed" in proc.stderr


def test_scene_path_outside_the_roots_names_scene_root(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from visfly_dist.cli import main

    scene = tmp_path / "mine" / "room.obj"
    scene.parent.mkdir()
    scene.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    other = tmp_path / "other"
    other.mkdir()
    args = ["train", "hover", "--set", f"scenes=[\"{scene}\"]", "--out", str(tmp_path / "x")]
    assert main([*args, "--scene-root", str(other)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is outside the scene roots" in err[0] and "--scene-root" in err[0]
    assert main([*args, "--scene-root", str(tmp_path / "nowhere")]) == 2
    assert "is not a folder" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_bad_task_exits_2_with_one_line(tmp_path: Path) -> None:
    proc = run_cli("train", "hovr", "--out", str(tmp_path / "x"))
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == ["visfly-dist train: error: unknown task 'hovr'; valid tasks: "
                                                "navigation, hover, landing, gap_crossing, racing, tracking, navigation_moving"]
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize(("setting", "message"), [
    ("max_episod_steps=20", "unknown setting(s) ['max_episod_steps'] for task 'hover'"),
    ('pool={"workerz": 1}', "unknown pool setting(s) ['workerz']"),
    ("max_episode_steps=0", "max_episode_steps=0 must be an int >= 1"),
    ("num_envs=4", "--set num_envs=... is not taken here: --num-envs sets it"),  # make_env would get it twice
    ("seed=3", "--set seed=... is not taken here: --seed sets it"),  # it would have won over --seed silently
])
def test_bad_setting_exits_2_before_any_worker(setting: str, message: str, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    from visfly_dist.cli import main

    assert main(["train", "hover", "--set", setting, "--out", str(tmp_path / "x")]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("visfly-dist train: error: ") and message in err[0]
    assert "starting the env" not in captured.out  # nothing is said to start before the settings are checked
    assert not (tmp_path / "x").exists()


def test_an_out_folder_that_holds_a_run_or_cannot_be_made_fails_before_any_worker(
        trained_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from visfly_dist.cli import main

    model = (trained_run / "final.zip").read_bytes()
    assert main(["train", "hover", "--out", str(trained_run), *TINY]) == 2
    err = capsys.readouterr().err
    assert f"--out {str(trained_run)!r} holds a run already (its config.json)" in err
    assert (trained_run / "final.zip").read_bytes() == model  # not overwritten
    (tmp_path / "a_file").write_text("")
    assert main(["train", "hover", "--out", str(tmp_path / "a_file" / "run"), *TINY]) == 2
    assert f"{str(tmp_path / 'a_file')!r} is not a folder" in capsys.readouterr().err


def test_eval_of_a_checkpoint_without_its_normalisation_fails_naming_the_file(
        trained_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from visfly_dist.cli import main

    copy = tmp_path / "copied"  # the model and the run's config, without final.norm.npz
    copy.mkdir()
    for name in ("final.zip", "config.json"):
        (copy / name).write_bytes((trained_run / name).read_bytes())
    assert main(["eval", "hover", "--checkpoint", str(copy / "final.zip"), "--episodes", "2"]) == 2
    err = capsys.readouterr().err
    assert f"{str(copy / 'final.norm.npz')!r} is missing: the run trained on normalised observations" in err
    assert missing_normalization(trained_run / "final.zip", None) is None  # beside it: nothing to say
    (copy / "config.json").unlink()  # nothing says whether the run normalised: a warning, not an error
    assert "evaluating without observation normalisation" in str(missing_normalization(copy / "final.zip", None))


def children(pid: int) -> list[int]:
    path = Path(f"/proc/{pid}/task/{pid}/children")
    return [int(p) for p in path.read_text().split()] if path.exists() else []


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    stat = Path(f"/proc/{pid}/stat")
    return stat.exists() and stat.read_text().split(")")[-1].split()[0] != "Z"


def as_from_a_terminal() -> None:
    """In the child: SIGINT at its default and unblocked, as in a shell. A child inherits an ignored
    or blocked SIGINT from this test process, where native libraries of earlier tests may have
    changed it; Python then never raises KeyboardInterrupt (seen in the full suite only)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_ctrl_c_or_sigterm_saves_the_model_and_stops_the_workers(tmp_path: Path, stop: signal.Signals) -> None:
    out = tmp_path / "run"
    proc = subprocess.Popen([*CLI, "train", "hover", "--timesteps", "10000000", "--out", str(out), *TINY],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=as_from_a_terminal)
    try:
        deadline = time.monotonic() + 90
        while not (out / "success_curve.csv").exists() or len((out / "success_curve.csv").read_text().splitlines()) < 2:
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read() if proc.poll() is not None else "timeout"
            time.sleep(0.2)
        workers = children(proc.pid)
        assert workers, "the run should have spawned its scene worker"
        proc.send_signal(stop)
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 128 + stop, stderr   # 130 for Ctrl-C, 143 for SIGTERM (Slurm's time limit, kill)
    assert "interrupted at" in stderr
    assert (out / "final.zip").is_file() and (out / "success_curve.png").is_file()
    assert not [pid for pid in workers if alive(pid)]


def test_an_error_that_ends_a_run_keeps_the_model_so_far(tmp_path: Path) -> None:
    out = tmp_path / "run"
    no_comeback = 'pool={"outage_limit_s": 2, "respawn": false}'  # every worker gone: NoWorkersError after 2 s
    proc = subprocess.Popen([*CLI, "train", "hover", "--timesteps", "10000000", "--out", str(out), *TINY,
                             "--set", no_comeback], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 90
        while not (out / "success_curve.csv").exists() or len((out / "success_curve.csv").read_text().splitlines()) < 2:
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read() if proc.poll() is not None else "timeout"
            time.sleep(0.2)
        for pid in children(proc.pid):
            os.kill(pid, signal.SIGKILL)
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 2 and "no scene worker reachable for outage_limit_s=2" in stderr, stderr
    assert f"the model so far is in {out / 'crash.zip'}" in stderr
    assert (out / "crash.zip").is_file() and (out / "crash.norm.npz").is_file() and not (out / "final.zip").exists()
    from stable_baselines3 import PPO

    assert PPO.load(out / "crash.zip", device="cpu").num_timesteps >= 128  # at least the first rollout's steps


def test_a_stop_swallowed_while_the_env_starts_still_stops_the_run(tmp_path: Path) -> None:
    """A Ctrl-C that lands in a library catching BaseException (trimesh's optional imports, while the
    first scene checks import it) is remembered: the run stops before its first step and saves."""
    from visfly_dist.training import stop
    from visfly_dist.training.config import TrainConfig
    from visfly_dist.training.ppo import train

    try:
        stop.ask(signal.SIGINT)  # what the CLI's handler does
    except KeyboardInterrupt:
        pass  # ... and what such a library does with it
    cfg = TrainConfig(task="hover", timesteps=10_000_000, num_envs=4, workers=1, n_steps=32, batch_size=64,
                      out=str(tmp_path / "run"), progress=False, overrides={"max_episode_steps": 20})
    result = train(cfg)
    assert result.interrupted and result.timesteps == 0 and (tmp_path / "run" / "final.zip").is_file()
    stop.raise_if_asked()  # taken by the trainer: a next run in this process starts afresh


def test_sigterm_stops_an_eval_and_its_workers(trained_run: Path) -> None:
    proc = subprocess.Popen([*CLI, "eval", "hover", "--checkpoint", str(trained_run / "final.zip"), "--episodes", "100000",
                             "--num-envs", "2", "--workers", "1"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert wait_for(lambda: children(proc.pid) or proc.poll() is not None, timeout=60)
        workers = children(proc.pid)
        time.sleep(3.0)  # into the episodes
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130 and "interrupted" in stderr, stderr  # unwound as Ctrl-C, not killed outright
    assert workers and not [pid for pid in workers if alive(pid)]
