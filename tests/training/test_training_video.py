"""Videos while training: ``TrainingVideo.maybe_record`` films in the background; ``train --video-every``."""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest
from gymnasium import spaces
from stable_baselines3 import PPO

from visfly_dist.cli import main
from visfly_dist.training.export import ObsNormalization
from visfly_dist.training.extractors import visfly_policy_kwargs
from visfly_dist.training.training_video import TrainingVideo


def tensorboard_tags(folder: Path) -> tuple[list[str], list[str]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(folder), size_guidance={"images": 0})
    acc.Reload()
    return acc.Tags()["images"], acc.Tags()["scalars"]


def test_maybe_record_films_one_episode_in_the_background(tmp_path: Path) -> None:
    space = spaces.Dict({"depth": spaces.Box(0.0, 20.0, (1, 64, 64), np.float32),
                         "state": spaces.Box(-np.inf, np.inf, (13,), np.float32),
                         "target": spaces.Box(-np.inf, np.inf, (4,), np.float32)})
    model = PPO("MultiInputPolicy", None, policy_kwargs=visfly_policy_kwargs(), device="cpu", seed=0, _init_setup_model=False)
    model.observation_space, model.action_space, model.n_envs = space, spaces.Box(-1, 1, (4,), np.float32), 1
    model._setup_model()
    norm = ObsNormalization(mean={"state": np.zeros(13), "target": np.zeros(4)}, var={"state": np.ones(13), "target": np.ones(4)})
    video = TrainingVideo("navigation", tmp_path, every=1000, env_settings={"seed": 0}, max_steps=12)
    try:
        assert not video.maybe_record(999, model.policy, norm)
        assert video.maybe_record(1024, model.policy, norm)
        assert video.wait(timeout=300)
        assert not video.maybe_record(1500, model.policy, norm)  # next due: 2000
        assert video.maybe_record(3100, model.policy, norm)  # next due after it: 4000
        assert video.wait(timeout=300)
        assert not video.maybe_record(3999, model.policy, norm)
    finally:
        video.close()
    assert not video.errors, video.errors
    assert video.written == [tmp_path / "videos" / "step-1024.gif", tmp_path / "videos" / "step-3100.gif"]
    frames = imageio.mimread(video.written[0])
    assert 1 <= len(frames) <= 12
    assert frames[0].shape[1] == 2 * frames[0].shape[0]  # the depth panel beside the chase camera
    images, scalars = tensorboard_tags(tmp_path / "videos")
    assert "videos/episode" in images and {"videos/episode_return", "videos/episode_length"} <= set(scalars)


@pytest.mark.parametrize("algo", ["ppo", "sb3-ppo"])
def test_train_with_video_every_writes_films(algo: str, tmp_path: Path) -> None:
    out = tmp_path / "run"
    argv = ["train", "hover", "--algo", algo, "--timesteps", "256", "--num-envs", "2", "--n-steps", "64",
            "--batch-size", "64", "--n-epochs", "1", "--workers", "1", "--checkpoint-every", "0", "--video-every", "128",
            "--out", str(out), "--quiet", "--device", "cpu", "--set", "max_episode_steps=16"]
    assert main(argv) == 0
    assert json.loads((out / "config.json").read_text())["video_every"] == 128
    films = sorted((out / "videos").glob("step-*.gif"))
    # films are due at 128 and 256 steps; one due while the last still runs is skipped, never queued
    assert films and {f.name for f in films} <= {"step-128.gif", "step-256.gif"}
    for film in films:
        assert 1 <= len(imageio.mimread(film)) <= 16
    assert "videos/episode" in tensorboard_tags(out / "videos")[0]
    assert (out / "final.zip").is_file()


def test_video_every_is_off_by_default_and_validated() -> None:
    from visfly_dist.errors import ConfigError
    from visfly_dist.training.config import TrainConfig

    assert TrainConfig(task="hover").resolved().video_every == 0   # without a host plan
    with pytest.raises(ConfigError, match="video_every"):
        TrainConfig(task="hover", video_every=-1).resolved().validate()
