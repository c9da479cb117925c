"""PPO training of a visfly-dist task, top to bottom: config, env, policy, loop, logging.

What a run writes in its folder (``TrainConfig.out``):

- ``config.json``: the full resolved configuration;
- ``events.out.tfevents.*`` and ``progress.csv``: SB3's losses plus ``charts/success_rate``,
  ``charts/mean_return``, ``charts/mean_length``, ``charts/steps_per_second`` (TensorBoard:
  ``tensorboard --logdir runs``);
- ``success_curve.csv`` / ``success_curve.png``: success rate and mean return against timesteps;
- ``checkpoints/step_<timesteps>.zip`` every ``checkpoint_every`` steps, and ``final.zip``
  (also written when the run is interrupted with Ctrl-C); each with ``*.norm.npz`` when
  observations are normalised (see :mod:`visfly_dist.training.checkpoints`).

Recurrent policies (``--recurrent``, ``TrainConfig.recurrent``): sb3-contrib's ``RecurrentPPO`` with
``MultiInputLstmPolicy``: the same extractor, then an LSTM (``RECURRENT_HIDDEN`` units; the actor and
the critic each have their own), then the 64-64 heads. Its hidden state is reset where an episode
starts and carried across rollouts; the update backpropagates through time over each env's rollout
(``n_steps`` long), cut at episode starts (truncated BPTT). It trains with SB3's loop (no update
threads, no ``--overlap``); with ``--algo ppo`` (the tensor trainer, which has no recurrent core) a
line says the run uses that loop instead. ``bptt``/``shac`` refuse it (ConfigError): they differentiate
through the dynamics and have no recurrent actor. Checkpoints are ``RecurrentPPO`` zips, which
``visfly-dist eval`` and ``visfly-dist export`` recognise.

The same pieces serve your own scripts: ``build_env(cfg)`` gives the wrapped VecEnv and
``build_model(cfg, env)`` the PPO model; or skip both and use ``make_env`` with
:func:`visfly_dist.training.extractors.visfly_policy_kwargs` directly.
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

import torch
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.logger import configure
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.vec_env import VecEnv, VecMonitor, VecNormalize

from visfly_dist.client.env_base import DroneEnvBase
from visfly_dist.errors import ConfigError
from visfly_dist.host import usable_cores
from visfly_dist.tasks import make_env
from visfly_dist.tasks.registry import task_class, task_config
from visfly_dist.training import stop
from visfly_dist.training.callbacks import StopWhenAsked, SuccessCallback
from visfly_dist.training.checkpoints import CheckpointEvery, Checkpoints, save_checkpoint, save_on_crash
from visfly_dist.training.config import PPO_ALGOS, TrainConfig, default_ppo
from visfly_dist.training.extractors import visfly_policy_kwargs
from visfly_dist.training.host_plan import apply_host_plan
from visfly_dist.training.memory import keep_freed_memory
from visfly_dist.training.overlap import OverlappedPPO, UpdateThreadsPPO
from visfly_dist.training.run import TrainResult, env_kwargs, vector_keys, write_config  # noqa: F401 - re-exported
from visfly_dist.training.tensor_ppo import TensorPPO
from visfly_dist.training.training_video import VideoCallback, video_for


def build_env(cfg: TrainConfig, worker_logs: Path | None = None) -> VecEnv:
    """``make_env`` wrapped in VecMonitor (episode stats) and, with ``cfg.normalize``, VecNormalize;
    ``worker_logs``: see :func:`~visfly_dist.training.run.env_kwargs`."""
    return wrap_env(cfg, make_env(cfg.task, num_envs=cfg.num_envs, **env_kwargs(cfg, worker_logs)))


def wrap_env(cfg: TrainConfig, task_env: DroneEnvBase) -> VecEnv:
    """``task_env`` in VecMonitor and, with ``cfg.normalize``, VecNormalize (SB3's loop)."""
    env: VecEnv = VecMonitor(task_env)
    if cfg.normalize:
        assert isinstance(env.observation_space, spaces.Dict)  # every task's
        keys = vector_keys(env.observation_space)
        env = VecNormalize(env, norm_obs=bool(keys), norm_obs_keys=keys or None, norm_reward=True, gamma=cfg.gamma)
    return env


RECURRENT_HIDDEN = 128
"""LSTM units of a ``--recurrent`` policy's actor (and, separately, its critic)."""


def build_model(cfg: TrainConfig, env: VecEnv) -> OnPolicyAlgorithm:
    """SB3 PPO with the VisFly-style extractor and actor/critic 64-64, logging to the run folder.

    For ``algo="ppo"`` it is plain SB3 ``PPO``, which holds the policy, its optimizer and the
    hyperparameters for :class:`TensorPPO` (and saves the ``.zip``). For ``"sb3-ppo"`` it is
    :class:`UpdateThreadsPPO` (plain PPO whose update uses every core while the workers are idle),
    or with ``cfg.overlap`` :class:`OverlappedPPO` (the next rollout collected while PPO learns).
    With ``cfg.recurrent`` it is sb3-contrib's ``RecurrentPPO`` (``MultiInputLstmPolicy``): the
    extractor, an LSTM of ``RECURRENT_HIDDEN`` units, the 64-64 heads.

    Raises:
        ConfigError: ``cfg`` is not resolved (:meth:`TrainConfig.resolved`).
    """
    if cfg.lr is None or cfg.n_steps is None or cfg.batch_size is None or cfg.n_epochs is None:
        raise ConfigError("build_model needs a resolved config (lr, n_steps, batch_size, n_epochs set): "
                          "pass cfg.resolved()")
    policy, lstm = "MultiInputPolicy", {}
    cls: type[OnPolicyAlgorithm]
    extra: dict[str, Any]
    if cfg.recurrent:
        from sb3_contrib import RecurrentPPO

        cls, extra, policy, lstm = RecurrentPPO, {}, "MultiInputLstmPolicy", {"lstm_hidden_size": RECURRENT_HIDDEN}
    elif cfg.algo == "ppo":
        cls, extra = PPO, {}
    elif cfg.overlap:
        cls, extra = OverlappedPPO, {}
    else:
        cls, extra = UpdateThreadsPPO, {"update_threads": cfg.update_threads}
    model = cls(
        policy,
        env,
        learning_rate=cfg.lr,
        n_steps=cfg.n_steps,
        batch_size=cfg.batch_size,
        n_epochs=cfg.n_epochs,
        gamma=cfg.gamma,
        gae_lambda=cfg.gae_lambda,
        ent_coef=cfg.ent_coef,
        clip_range=cfg.clip_range,
        policy_kwargs={**visfly_policy_kwargs(cfg.backbone), "log_std_init": cfg.log_std_init, **lstm},
        seed=cfg.seed,
        device=cfg.device,
        verbose=0,
        **extra,
    )
    model.set_logger(configure(str(cfg.out), ["tensorboard", "csv"]))
    return model


def train(cfg: TrainConfig) -> TrainResult:
    """Run PPO on ``cfg.task`` (``algo="ppo"``: :class:`TensorPPO`; ``"sb3-ppo"``: SB3's loop);
    Ctrl-C stops early, saves ``final.zip`` and closes the env.

    Raises:
        ConfigError: a bad setting, raised before any worker starts.
    """
    cfg = replace(cfg, algo=cfg.algo if cfg.algo in PPO_ALGOS else default_ppo(cfg.task))
    if cfg.recurrent and cfg.algo == "ppo":
        print("--recurrent: the tensor trainer (--algo ppo) has no recurrent core; training with sb3-contrib's "
              "RecurrentPPO in SB3's loop (sb3-ppo)", flush=True)
        cfg = replace(cfg, algo="sb3-ppo")
    cfg = apply_host_plan(cfg, log=lambda line: print(line, flush=True) if cfg.progress else None).resolved().validate()
    torch.set_num_threads(cfg.threads)
    keep_freed_memory()
    if cfg.recurrent and cfg.overlap:
        print("--recurrent: RecurrentPPO collects and learns in turn; --overlap does not apply", flush=True)
        cfg = replace(cfg, overlap=False)
    assert cfg.out is not None and cfg.timesteps is not None  # resolved() and validate() set them
    run_dir, timesteps = Path(cfg.out), cfg.timesteps
    tensor = cfg.algo == "ppo"
    logs = run_dir / "workers"  # kept with the run: a worker that failed can be read about afterwards
    # checked here, so that a bad task setting fails before anything is said to start
    env_config = task_config(cfg.task, num_envs=cfg.num_envs, **env_kwargs(cfg, logs))
    if cfg.progress:
        print(f"starting the env: {cfg.num_envs} agents, their scenes loaded by {cfg.workers} local worker(s)"
              if cfg.workers else f"starting the env: {cfg.num_envs} agents, scenes loaded by remote workers", flush=True)
    started = time.monotonic()
    task_env = task_class(cfg.task)(env_config)
    env = task_env if tensor else wrap_env(cfg, task_env)
    if cfg.progress:
        print(f"env ready in {time.monotonic() - started:.1f} s", flush=True)
    interrupted = False
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        write_config(cfg, run_dir)
        model = build_model(cfg, env)
        success = SuccessCallback(run_dir, timesteps, verbose=int(cfg.progress))
        video = video_for(cfg)
        learn: Callable[[], object]
        if tensor:
            assert isinstance(model, PPO) and isinstance(env, DroneEnvBase)  # algo "ppo": plain PPO on the task's env
            trainer = TensorPPO(model, env, normalize=cfg.normalize, overlap=bool(cfg.overlap),
                                update_threads=cfg.update_threads, cpu_cores=usable_cores())
            checkpoints = Checkpoints(run_dir / "checkpoints", cfg.checkpoint_every, trainer.save)

            def on_rollout_end(n: int) -> None:
                stop.raise_if_asked()
                checkpoints(n)
                if video is not None:
                    video.maybe_record(n, model.policy, trainer.norm)

            learn = lambda: trainer.learn(timesteps, success, on_rollout_end=on_rollout_end)  # noqa: E731
            save, phases = trainer.save, trainer.phase_seconds
        else:
            callbacks = [success, CheckpointEvery(run_dir / "checkpoints", cfg.checkpoint_every), StopWhenAsked()]
            callbacks += [VideoCallback(video)] if video is not None else []
            learn = lambda: model.learn(timesteps, callback=callbacks, progress_bar=False)  # noqa: E731
            save, phases = (lambda path: save_checkpoint(model, path)), getattr(model, "phase_seconds", {})
        try:
            stop.raise_if_asked()  # a stop swallowed while the env started
            learn()
        except KeyboardInterrupt:
            stop.taken()
            interrupted = True
            print(f"interrupted at {model.num_timesteps:,} steps; saving the model", file=sys.stderr, flush=True)
            if not tensor:
                success.on_training_end()
        except Exception:
            save_on_crash(save, run_dir / "crash.zip", model.num_timesteps)
            raise
        if video is not None:
            video.close(wait=True)  # the last film, if one is running
        final = save(run_dir / "final.zip")
        summary = {**success.summary(), **phases}
        result = TrainResult(run_dir, final, model.num_timesteps, interrupted, summary, cfg)
    finally:
        env.close()
    s = result.summary
    print(
        f"done: {result.timesteps:,} steps, success rate {s['success_rate']:.2f}, mean return {s['mean_return']:.2f}; "
        f"model {final}",
        flush=True,
    )
    return result
