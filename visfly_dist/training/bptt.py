"""BPTT: back-propagation through time over the differentiable env, top to bottom.

The actor is deterministic (``tanh`` of an MLP on the VisFly extractor's features). Each update:

1. roll the env ``horizon`` steps (default 32) with gradients kept through the batched dynamics and
   the rewards (images enter as constants);
2. loss ``= -1/(H N) sum_agents sum_t gamma^(t - t0) r_t``, the discount restarting at 1 when an
   agent's episode ends (``t0`` its start; a reset agent's state is replaced by ``torch.where``,
   which cuts its gradient);
3. backward, clip the gradient norm to ``MAX_GRAD_NORM``, Adam step (the learning rate decays
   linearly to a tenth of ``lr`` over the run);
4. cut the graph (``env.detach()``) and go on from where the agents are.

A worker dying mid-window: its agents come back ``lost`` (the env truncates and resets them); the
window ends at that step, the lost agents' last reward is dropped, and the log says so.

What a run writes in its folder: ``config.json``; ``progress.csv`` and TensorBoard events
(``losses/actor_loss``, ``losses/grad_norm``, ``charts/*``); ``success_curve.csv``/``.png`` (as
PPO's); ``checkpoints/step_<timesteps>.npz`` and ``final.npz`` (the actor's parameters, no
pickle; :func:`load_actor` reads them, and the actor's ``predict`` works with
:func:`visfly_dist.training.evaluation.evaluate`).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from gymnasium import spaces
from stable_baselines3.common.logger import configure
from stable_baselines3.common.vec_env import VecEnv

from visfly_dist.client.env_base import DroneEnvBase
from visfly_dist.tasks import make_env
from visfly_dist.training import stop
from visfly_dist.training.checkpoints import save_on_crash
from visfly_dist.training.config import TrainConfig
from visfly_dist.training.diff_common import (
    DiffActor,
    EpisodeLog,
    clip_and_step,
    decay_lr,
    detach_obs,
    load_params,
    rollout_window,
    save_params,
)
from visfly_dist.training.host_plan import check_device
from visfly_dist.training.run import TrainResult, env_kwargs, write_config


def build_diff_env(cfg: TrainConfig, worker_logs: Path | None = None) -> DroneEnvBase:
    """The task's env with gradients through dynamics and rewards (``requires_grad=True``);
    ``worker_logs``: see :func:`~visfly_dist.training.run.env_kwargs`."""
    return make_env(cfg.task, num_envs=cfg.num_envs, requires_grad=True, **env_kwargs(cfg, worker_logs))


def first_observation(env: DroneEnvBase) -> dict[str, torch.Tensor]:
    """Reset ``env`` and return its observation as tensors (no graph: a fresh state has none)."""
    return {k: torch.as_tensor(v, device=env.device) for k, v in env.reset().items()}


def load_actor(checkpoint: Path, env: VecEnv, backbone: str = "visfly-cnn") -> DiffActor:
    """The actor of a BPTT/SHAC checkpoint (``.npz``), for ``env``'s observation space."""
    assert isinstance(env.observation_space, spaces.Dict)  # every task's observation space
    actor = DiffActor(env.observation_space, backbone)
    load_params({"actor": actor}, checkpoint)
    return actor


@dataclass
class Progress:
    """Counters of a run."""

    timesteps: int = 0
    windows: int = 0
    next_checkpoint: int = 0


def report_lost(window_steps: int, horizon: int, lost: int, timesteps: int) -> None:
    """Say on stderr that a window was truncated because agents were lost."""
    print(f"[{timesteps:,}] {lost} agent(s) lost (worker gone): window truncated at step {window_steps}/{horizon}, "
          "their last reward dropped", file=sys.stderr, flush=True)


def train_bptt(cfg: TrainConfig) -> TrainResult:
    """Run BPTT on ``cfg.task``; Ctrl-C stops early and saves ``final.npz``.

    Raises:
        ConfigError: a bad setting, raised before any worker starts.
    """
    cfg = replace(cfg, algo="bptt", device=check_device(cfg.device)).resolved().validate()
    # resolved() fills these in and validate() checks them
    assert cfg.out is not None and cfg.timesteps is not None and cfg.horizon is not None and cfg.lr is not None
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    run_dir = Path(cfg.out)
    env = build_diff_env(cfg, run_dir / "workers")
    interrupted = False
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        write_config(cfg, run_dir)
        actor = DiffActor(env.observation_space, cfg.backbone).to(cfg.device)
        optimizer = torch.optim.Adam(actor.parameters(), lr=cfg.lr)
        log = EpisodeLog(run_dir, cfg.timesteps, configure(str(run_dir), ["tensorboard", "csv"]), verbose=cfg.progress)
        p = Progress(next_checkpoint=cfg.checkpoint_every)
        obs = first_observation(env)
        try:
            while p.timesteps < cfg.timesteps:
                stop.raise_if_asked()  # a stop swallowed on its way
                window = rollout_window(env, actor, obs, cfg.horizon, cfg.gamma)
                p.timesteps += window.steps * env.num_envs
                optimizer.zero_grad(set_to_none=True)
                window.loss.backward()
                decay_lr(optimizer, cfg.lr, p.timesteps, cfg.timesteps)
                grad_norm, stepped = clip_and_step(optimizer, list(actor.parameters()))
                env.detach()
                obs = detach_obs(window.next_obs)
                p.windows += 1
                if window.lost_agents:
                    report_lost(window.steps, cfg.horizon, window.lost_agents, p.timesteps)
                log.add(window.episodes)
                log.dump(p.timesteps, {"losses/actor_loss": float(window.loss.detach()), "losses/grad_norm": grad_norm,
                                       "losses/skipped_update": float(not stepped),
                                       "charts/lost_agents": float(window.lost_agents)})
                if cfg.checkpoint_every and p.timesteps >= p.next_checkpoint:
                    save_params({"actor": actor}, run_dir / "checkpoints" / f"step_{p.timesteps}.npz")
                    p.next_checkpoint += cfg.checkpoint_every
        except KeyboardInterrupt:
            stop.taken()
            interrupted = True
            print(f"interrupted at {p.timesteps:,} steps; saving the actor", file=sys.stderr, flush=True)
        except Exception:
            save_on_crash(lambda path: save_params({"actor": actor}, path), run_dir / "crash.npz", p.timesteps)
            raise
        log.close()
        final = save_params({"actor": actor}, run_dir / "final.npz")
        result = TrainResult(run_dir, final, p.timesteps, interrupted, log.summary())
    finally:
        env.close()
    s = result.summary
    print(f"done: {result.timesteps:,} steps, success rate {s['success_rate']:.2f}, "
          f"mean return {s['mean_return']:.2f}; actor {final}", flush=True)
    return result
