"""Evaluating a trained policy: success rate, returns, lengths, collisions, and a video.

Episodes are counted per agent up to a quota of ``ceil(episodes / num_envs)`` each, so that short
(often failed) episodes do not crowd out long ones; the first ``episodes`` counted are reported.
Returns are the env's raw rewards (``info["episode"]`` of ``VecMonitor``), never the normalised ones.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecEnv, VecMonitor, VecNormalize

from visfly_dist.tasks import make_env
from visfly_dist.errors import ConfigError
from visfly_dist.training.checkpoints import load_normalization, norm_path
from visfly_dist.training.config import TrainConfig
from visfly_dist.training.ppo import env_kwargs
from visfly_dist.training.video import VideoRecorder


@dataclass
class EvalStats:
    """Outcome of an evaluation.

    Attributes:
        episodes: episodes counted.
        success_rate: share of episodes ending in success.
        mean_return: mean undiscounted return.
        mean_length: mean episode length, steps.
        collisions: episodes that ended in a collision.
        out_of_bounds: episodes that ended by leaving the flight box.
        video_frames: frames written to the video (0 without one).
        video_episode_length: length of the filmed episode, steps (0 without a video).
    """

    episodes: int
    success_rate: float
    mean_return: float
    mean_length: float
    collisions: int
    out_of_bounds: int
    video_frames: int = 0
    video_episode_length: int = 0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def find_run_config(checkpoint: Path) -> TrainConfig | None:
    """The ``config.json`` of the run a checkpoint belongs to (its folder or the one above), if any."""
    for folder in (checkpoint.parent, checkpoint.parent.parent):
        path = folder / "config.json"
        if path.is_file():
            return TrainConfig.from_dict(json.loads(path.read_text()))
    return None


def load_policy(checkpoint: Path, env: VecEnv, device: str = "cpu") -> tuple[PPO, VecEnv]:
    """Load a PPO checkpoint for ``env``; wraps ``env`` in its saved normalisation when there is one."""
    if not checkpoint.is_file():
        raise ConfigError(f"checkpoint {str(checkpoint)!r} does not exist; pass a .zip written by 'visfly-dist train'")
    stats = norm_path(checkpoint)
    if stats.is_file():
        env = load_normalization(env, stats)
    try:
        model = PPO.load(checkpoint, env=env, device=device)
    except ValueError as exc:
        raise ConfigError(f"checkpoint {checkpoint} does not fit this env ({exc}); evaluate with the training's task and --set settings") from exc
    return model, env


def evaluate(model: PPO, env: VecEnv, episodes: int, deterministic: bool = True,
             recorder: VideoRecorder | None = None) -> EvalStats:
    """Run ``model`` on ``env`` until ``episodes`` episodes are counted.

    Args:
        model: the policy.
        env: the (possibly normalising) VecEnv the model was loaded with.
        episodes: episodes to count (>= 1).
        deterministic: take the mean action instead of sampling.
        recorder: when given, films agent ``recorder.agent`` during its first episode: one frame per
            observation it acts on, so the video has as many frames as that episode has steps.
    """
    if episodes < 1:
        raise ConfigError(f"episodes={episodes!r} must be >= 1")
    n = env.num_envs
    quota = math.ceil(episodes / n)
    counted = np.zeros(n, dtype=np.int64)
    results: list[tuple[bool, float, int, bool, bool]] = []
    filming = recorder is not None
    obs = env.reset()
    step, ret, filmed_length = 0, 0.0, 0
    while len(results) < episodes:
        if filming:
            recorder.add(obs, f"step {step}  return {ret:.2f}")
        actions, _ = model.predict(obs, deterministic=deterministic)
        obs, rewards, dones, infos = env.step(actions)
        if filming:
            raw = env.get_original_reward() if isinstance(env, VecNormalize) else rewards
            step, ret = step + 1, ret + float(raw[recorder.agent])
        for i in np.flatnonzero(dones):
            info = infos[i]
            if filming and i == recorder.agent:
                filming, filmed_length = False, int(info["episode"]["l"])
            if counted[i] < quota and len(results) < episodes:
                counted[i] += 1
                ep = info["episode"]
                results.append((bool(info.get("is_success")), float(ep["r"]), int(ep["l"]),
                                bool(info.get("collision")), bool(info.get("out_of_bounds"))))
    arr = np.asarray(results, dtype=np.float64)
    return EvalStats(
        episodes=len(results),
        success_rate=float(arr[:, 0].mean()),
        mean_return=float(arr[:, 1].mean()),
        mean_length=float(arr[:, 2].mean()),
        collisions=int(arr[:, 3].sum()),
        out_of_bounds=int(arr[:, 4].sum()),
        video_frames=len(recorder.frames) if recorder is not None else 0,
        video_episode_length=filmed_length,
    )


def build_eval_env(task: str, num_envs: int | None, seed: int, run_cfg: TrainConfig | None,
                   overrides: dict[str, Any], pool: dict[str, Any]) -> VecEnv:
    """``make_env`` with the training run's settings (when known), then the given changes."""
    cfg = run_cfg if run_cfg is not None and run_cfg.task == task else TrainConfig(task=task)
    cfg = cfg.resolved()
    cfg.seed = seed
    cfg.overrides = {**cfg.overrides, **overrides}
    for key, value in pool.items():
        if value is not None:
            setattr(cfg, key, value)
    return VecMonitor(make_env(task, num_envs=num_envs or cfg.num_envs, **env_kwargs(cfg)))
