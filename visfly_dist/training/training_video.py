"""Videos while training: every ``every`` env steps, one deterministic episode filmed in the background.

The film is the eval GIF of :mod:`visfly_dist.training.video` (the agent's camera beside a chase
camera), written to ``RUN/videos/step-<n>.gif`` and to TensorBoard (``RUN/videos``: up to
``TB_FRAMES`` evenly spaced frames as an image sequence, ``videos/episode``, and the episode's
return and length). Training does not wait for it: at the due step the policy's weights are copied
(a ``state_dict`` snapshot on the CPU) with the observation statistics, and a background thread
runs the episode on its own small env (one scene, one local worker, a run id of its own; the task's
``evaluation_defaults`` applied, seed ``seed``) with a private copy of the policy. When the last
film is still running at the next due step, that one is skipped (counted in ``skipped``).

Two ways in:

- any trainer: ``video.maybe_record(env_steps, policy, normalization)`` once in a while (each
  rollout's end, say); ``policy`` is an SB3 policy (``model.policy``; its ``predict`` is used) or a
  ``torch.nn.Module`` mapping a dict of float tensors ``(N, ...)`` to deterministic actions ``(N, 4)``;
  ``normalization`` what turns raw observations into the policy's (a ``VecNormalize``, TensorPPO's
  ``Normalizer``, an :class:`~visfly_dist.training.export.ObsNormalization` or ``None``);
- SB3's ``model.learn``: the callback :class:`VideoCallback`.

Off by default (``visfly-dist train --video-every STEPS``): on a 2-core host the film's rendering
takes CPU from training.
"""

from __future__ import annotations

import copy
import queue
import sys
import threading
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecNormalize

from visfly_dist.training.export import ObsNormalization

TB_FRAMES = 8
"""Frames of each film shown in TensorBoard (evenly spaced, first and last included)."""


def as_normalization(source: Any) -> ObsNormalization | None:
    """A frozen copy of the observation statistics of ``source`` (see the module docstring)."""
    if source is None or isinstance(source, ObsNormalization):
        return copy.deepcopy(source)
    if isinstance(getattr(source, "obs_rms", None), dict):  # VecNormalize and what looks like one
        return ObsNormalization.of(source)
    if hasattr(source, "obs_moments"):  # TensorPPO's Normalizer
        from visfly_dist.training import tensor_ppo

        moments = source.obs_moments
        return ObsNormalization(mean={k: m.mean.detach().cpu().numpy().copy() for k, m in moments.items()},
                                var={k: m.var.detach().cpu().numpy().copy() for k, m in moments.items()},
                                clip=float(getattr(tensor_ppo, "CLIP_OBS", 10.0)), epsilon=float(getattr(tensor_ppo, "EPSILON", 1e-8)))
    raise TypeError(f"cannot read observation statistics from {type(source).__name__}")


class TrainingVideo:
    """Films one deterministic episode every ``every`` env steps without stalling training.

    Args:
        task: the task trained.
        run_dir: the run folder (videos go to ``run_dir/videos``).
        every: env steps between films (0: never).
        env_settings: ``make_env`` keyword arguments of the run (:func:`~visfly_dist.training.ppo.env_kwargs`);
            the pool is replaced by one local worker of its own.
        seed: env seed of every film (the same starts each time, so films compare).
        max_steps: length limit of a film, steps (default: the task's episode limit).
        tensorboard: also write to TensorBoard.
    """

    def __init__(self, task: str, run_dir: str | Path, every: int, env_settings: dict[str, Any] | None = None,
                 seed: int = 12345, max_steps: int | None = None, tensorboard: bool = True) -> None:
        self.task, self.run_dir, self.every = task, Path(run_dir), int(every)
        self.env_settings = dict(env_settings or {})
        self.seed, self.max_steps, self.tensorboard = seed, max_steps, tensorboard
        self.written: list[Path] = []
        self.skipped = 0
        self.errors: list[str] = []
        self._next = self.every
        self._jobs: queue.Queue = queue.Queue(maxsize=1)
        self._idle = threading.Event()
        self._idle.set()
        self._thread: threading.Thread | None = None
        self._policy: Any = None
        self._lstm_state: Any = None  # a recurrent policy's LSTM state during a film
        self._env: Any = None
        self._writer: Any = None

    # ----- the training side ------------------------------------------------------------------

    def due(self, env_steps: int) -> bool:
        return self.every > 0 and env_steps >= self._next

    def maybe_record(self, env_steps: int, policy: torch.nn.Module, normalization: Any = None) -> bool:
        """Start filming when ``env_steps`` reached the next multiple of ``every``; returns whether it did.

        Costs the training loop a copy of the weights; the episode runs in the background.
        """
        if not self.due(env_steps):
            return False
        self._next = (env_steps // self.every + 1) * self.every
        if not self._idle.is_set():
            self.skipped += 1
            print(f"video: the film before step {env_steps:,} is still running; skipped this one", file=sys.stderr, flush=True)
            return False
        state = {k: v.detach().to("cpu", copy=True) for k, v in policy.state_dict().items()}
        if self._policy is None:
            self._policy = copy.deepcopy(policy).to("cpu")
        self._idle.clear()
        self._jobs.put((int(env_steps), state, as_normalization(normalization)))
        if self._thread is None:
            self._thread = threading.Thread(target=self._serve, name="training-video", daemon=True)
            self._thread.start()
        return True

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the film in progress (if any) is written; whether it is."""
        return self._idle.wait(timeout)

    def close(self, wait: bool = True) -> None:
        """Let the film in progress finish (``wait``), stop the thread, close the env and the writer."""
        if self._thread is not None:
            if wait:
                self._idle.wait()
            self._jobs.put(None)
            self._thread.join(timeout=None if wait else 1.0)
            self._thread = None

    # ----- the background thread -------------------------------------------------------------

    def _serve(self) -> None:
        try:
            while True:
                job = self._jobs.get()
                if job is None:
                    return
                try:
                    self._film(*job)
                except Exception as exc:  # a film must never take training down
                    self.errors.append(f"step {job[0]}: {type(exc).__name__}: {exc}")
                    print(f"video: filming at step {job[0]:,} failed: {exc}", file=sys.stderr, flush=True)
                finally:
                    self._idle.set()
        finally:
            if self._env is not None:
                self._env.close()
                self._env = None
            if self._writer is not None:
                self._writer.close()
                self._writer = None

    def _make_env(self) -> Any:
        from visfly_dist.aggregator.config import PoolConfig
        from visfly_dist.tasks import make_env, task_class

        config_class = task_class(self.task).config_class
        settings = {**{k: v for k, v in self.env_settings.items() if k in config_class.field_names()},
                    **config_class.evaluation_defaults}
        pool = settings.get("pool")
        settings["pool"] = replace(pool, num_local_workers=1, connect=(), run_id=None) if isinstance(pool, PoolConfig) \
            else PoolConfig(num_local_workers=1, backend="raycast")
        settings.pop("num_envs", None)
        team = config_class(**settings).agents_per_scene
        return make_env(self.task, num_envs=team, **settings)

    def _act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        policy = self._policy
        if hasattr(policy, "lstm_actor"):  # recurrent (train --recurrent): carry the LSTM state through the episode
            action, self._lstm_state = policy.predict(obs, state=self._lstm_state, deterministic=True)
            return action
        if hasattr(policy, "predict"):
            return policy.predict(obs, deterministic=True)[0]
        with torch.no_grad():
            action = policy({k: torch.as_tensor(np.asarray(v, np.float32)) for k, v in obs.items()})
        return np.clip(action.cpu().numpy(), -1.0, 1.0)

    def _film(self, env_steps: int, state: dict[str, torch.Tensor], norm: ObsNormalization | None) -> Path:
        from visfly_dist.training.video import VideoRecorder

        torch.set_num_threads(1)
        if self._env is None:
            self._env = self._make_env()
        env = self._env
        self._policy.load_state_dict(state)
        if hasattr(self._policy, "set_training_mode"):
            self._policy.set_training_mode(False)
        else:
            self._policy.eval()
        recorder = VideoRecorder(env, agent=0)
        self._lstm_state = None  # a recurrent policy's state: zeros at the episode's start
        limit = int(self.max_steps or env.config.max_episode_steps)
        env.seed(self.seed)
        obs = env.reset()
        total, length = 0.0, 0
        try:
            for length in range(1, limit + 1):
                recorder.add(obs, f"step {env_steps:,}  t {length - 1}  return {total:.2f}")
                actions = self._act(norm.normalize(obs) if norm is not None else obs)
                obs, rewards, dones, _ = env.step(actions)
                total += float(rewards[0])
                if dones[0]:
                    break
            path = recorder.save(self.run_dir / "videos" / f"step-{env_steps}.gif")
            if self.tensorboard:
                self._to_tensorboard(env_steps, recorder.frames, total, length)
        finally:
            recorder.close()
        self.written.append(path)
        return path

    def _to_tensorboard(self, env_steps: int, frames: list[np.ndarray], total: float, length: int) -> None:
        if self._writer is None:
            from torch.utils.tensorboard import SummaryWriter

            self._writer = SummaryWriter(str(self.run_dir / "videos"))
        picks = np.unique(np.linspace(0, len(frames) - 1, min(TB_FRAMES, len(frames))).round().astype(int))
        self._writer.add_images("videos/episode", np.stack([frames[i] for i in picks]), env_steps, dataformats="NHWC")
        self._writer.add_scalar("videos/episode_return", total, env_steps)
        self._writer.add_scalar("videos/episode_length", length, env_steps)
        self._writer.flush()


class VideoCallback(BaseCallback):
    """:class:`TrainingVideo` as an SB3 callback: checks every step, passes the VecNormalize
    statistics along, and lets the last film finish when training ends."""

    def __init__(self, video: TrainingVideo) -> None:
        super().__init__()
        self.video = video

    def _on_step(self) -> bool:
        if self.video.due(self.num_timesteps):
            venv = self.model.get_env()
            self.video.maybe_record(self.num_timesteps, self.model.policy, venv if isinstance(venv, VecNormalize) else None)
        return True

    def _on_training_end(self) -> None:
        self.video.close(wait=True)


def video_for(cfg: Any) -> TrainingVideo | None:
    """The :class:`TrainingVideo` of a resolved ``TrainConfig`` (``None`` when ``video_every`` is 0)."""
    every = int(getattr(cfg, "video_every", 0) or 0)
    if every <= 0:
        return None
    from visfly_dist.training.run import env_kwargs

    return TrainingVideo(cfg.task, cfg.out, every, env_kwargs(cfg), seed=cfg.seed + 12345)
