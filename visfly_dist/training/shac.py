"""SHAC (Xu et al. 2022): short-horizon actor-critic over the differentiable env, top to bottom.

As BPTT (:mod:`visfly_dist.training.bptt`), with a learned value closing every window:

1. roll ``horizon`` steps with gradients; the actor's loss is
   ``-1/(H N) sum (sum_t gamma^(t - t0) r_t + bootstrap)``, where an episode truncated inside the
   window bootstraps with ``gamma V(terminal obs)``, a terminated one with nothing, and every agent
   still running at the end with ``gamma^(H - t0) V(obs_H)``; ``V`` is the target critic, and the
   gradient flows through its input (the state), not its weights, and is scaled from 0 to 1 over
   the first ``VALUE_RAMP_WINDOWS`` windows, while the critic is still untrained;
2. backward, clip, Adam step of the actor (its learning rate decays linearly to a tenth of ``lr``);
   cut the graph;
3. TD(lambda) value targets over the window (``lambda = gae_lambda``) from the detached rewards and
   target-critic values; ``n_epochs`` passes of minibatches (``batch_size``) of MSE on the critic,
   in units of the running scale of its targets (:meth:`Critic.update_scale`);
4. the target critic follows: ``target = alpha target + (1 - alpha) critic`` (``TARGET_ALPHA``).

Lost agents (a worker died) end the window as in BPTT; their last step is left out of the critic's
targets. The run folder is BPTT's; checkpoints hold ``actor/*`` and ``critic/*``.
"""

from __future__ import annotations

import copy
import sys
from dataclasses import replace
from pathlib import Path
from typing import Callable

import torch
from stable_baselines3.common.logger import configure

from visfly_dist.training import stop
from visfly_dist.training.bptt import Progress, build_diff_env, first_observation, report_lost
from visfly_dist.training.checkpoints import save_on_crash
from visfly_dist.training.config import TrainConfig
from visfly_dist.training.diff_common import (
    Critic,
    DiffActor,
    EpisodeLog,
    Obs,
    Window,
    clip_and_step,
    decay_lr,
    detach_obs,
    rollout_window,
    save_params,
)
from visfly_dist.training.host_plan import check_device
from visfly_dist.training.run import TrainResult, write_config

TARGET_ALPHA = 0.2
"""Share of the old target critic kept at each update (SHAC's ``target_critic_alpha``)."""

VALUE_RAMP_WINDOWS = 50
"""The actor's gradient through the critic's value grows from 0 to full over this many windows,
while the critic learns (its value in the loss, and in the critic's targets, is always whole)."""


def scale_gradient(x: torch.Tensor, weight: float) -> torch.Tensor:
    """``x`` whose gradient is scaled by ``weight`` (its value unchanged)."""
    return x if weight == 1.0 else weight * x + (1 - weight) * x.detach()


def ramped(critic: Callable[[Obs], torch.Tensor], weight: float) -> Callable[[Obs], torch.Tensor]:
    """``critic`` whose output's gradient is scaled by ``weight`` (see :func:`scale_gradient`)."""
    return lambda obs: scale_gradient(critic(obs), weight)


def lambda_returns(window: Window, values: torch.Tensor, gamma: float, lam: float) -> torch.Tensor:
    """``(T, N)`` TD(lambda) targets of the window's observations.

    Args:
        window: the rollout (rewards, dones, bootstrap values after each step).
        values: ``(T, N)`` target-critic values of the observations acted on.
        gamma: discount.
        lam: lambda; the return is cut (bootstrapped from ``window.next_values``) where an episode
            ended and at the window's end.
    """
    out = torch.zeros_like(window.rewards)
    g = torch.zeros_like(window.rewards[0])
    last = window.steps - 1
    for t in range(last, -1, -1):
        if t == last:
            ahead = window.next_values[t]
        else:
            ahead = torch.where(window.done[t], window.next_values[t], (1 - lam) * values[t + 1] + lam * g)
        g = window.rewards[t] + gamma * ahead
        out[t] = g
    return out


def fit_critic(critic: Critic, optimizer: torch.optim.Optimizer, obs: dict[str, torch.Tensor], targets: torch.Tensor,
               epochs: int, batch_size: int, generator: torch.Generator) -> float:
    """``epochs`` passes of shuffled minibatches of MSE towards ``targets`` (in the critic's normalised
    units, see :meth:`Critic.normalize`); the last pass's mean loss."""
    n = len(targets)
    loss_sum = 0.0
    for _ in range(epochs):
        order = torch.randperm(n, generator=generator)
        loss_sum, batches = 0.0, 0
        for start in range(0, n, batch_size):
            idx = order[start:start + batch_size]
            loss = (critic.normalized({k: v[idx] for k, v in obs.items()}) - targets[idx]).square().mean()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            clip_and_step(optimizer, list(critic.parameters()))
            loss_sum, batches = loss_sum + float(loss.detach()), batches + 1
        loss_sum /= batches
    return loss_sum


def train_shac(cfg: TrainConfig) -> TrainResult:
    """Run SHAC on ``cfg.task``; Ctrl-C stops early and saves ``final.npz``.

    Raises:
        ConfigError: a bad setting, raised before any worker starts.
    """
    cfg = replace(cfg, algo="shac", device=check_device(cfg.device)).resolved().validate()
    # resolved() fills these in and validate() checks them
    assert (cfg.out is not None and cfg.timesteps is not None and cfg.horizon is not None and cfg.lr is not None
            and cfg.batch_size is not None and cfg.n_epochs is not None)
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    run_dir = Path(cfg.out)
    env = build_diff_env(cfg, run_dir / "workers")
    interrupted = False
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        write_config(cfg, run_dir)
        actor = DiffActor(env.observation_space, cfg.backbone).to(cfg.device)
        critic = Critic(env.observation_space, cfg.backbone).to(cfg.device)
        target = copy.deepcopy(critic).requires_grad_(False)
        actor_opt = torch.optim.Adam(actor.parameters(), lr=cfg.lr)
        critic_opt = torch.optim.Adam(critic.parameters(), lr=cfg.lr)
        shuffle = torch.Generator().manual_seed(cfg.seed)
        log = EpisodeLog(run_dir, cfg.timesteps, configure(str(run_dir), ["tensorboard", "csv"]), verbose=cfg.progress)
        p = Progress(next_checkpoint=cfg.checkpoint_every)
        obs = first_observation(env)
        try:
            while p.timesteps < cfg.timesteps:
                stop.raise_if_asked()  # a stop swallowed on its way
                # Actor: the window's loss, through the dynamics and the target critic's input.
                weight = min(1.0, p.windows / VALUE_RAMP_WINDOWS)
                window = rollout_window(env, actor, obs, cfg.horizon, cfg.gamma,
                                        value=ramped(target, weight))
                p.timesteps += window.steps * env.num_envs
                actor_opt.zero_grad(set_to_none=True)
                window.loss.backward()
                decay_lr(actor_opt, cfg.lr, p.timesteps, cfg.timesteps)
                grad_norm, stepped = clip_and_step(actor_opt, list(actor.parameters()))
                env.detach()
                obs = detach_obs(window.next_obs)
                if window.lost_agents:
                    report_lost(window.steps, cfg.horizon, window.lost_agents, p.timesteps)

                # Critic: TD(lambda) targets from the target critic, on the agents' real steps.
                stacked = {k: torch.cat([o[k] for o in window.obs]) for k in window.obs[0]}
                with torch.no_grad():
                    values = target(stacked).reshape(window.steps, -1)
                    targets = lambda_returns(window, values, cfg.gamma, cfg.gae_lambda)
                keep = window.valid.flatten()
                critic.update_scale(targets.flatten()[keep])
                critic_loss = fit_critic(critic, critic_opt, {k: v[keep] for k, v in stacked.items()},
                                         critic.normalize(targets.flatten()[keep]), cfg.n_epochs, cfg.batch_size,
                                         shuffle)
                with torch.no_grad():
                    for t_param, param in zip(target.parameters(), critic.parameters()):
                        t_param.lerp_(param, 1 - TARGET_ALPHA)
                    for t_buf, buf in zip(target.buffers(), critic.buffers()):
                        t_buf.copy_(buf)
                p.windows += 1

                log.add(window.episodes)
                log.dump(p.timesteps, {"losses/actor_loss": float(window.loss.detach()), "losses/critic_loss": critic_loss,
                                       "losses/grad_norm": grad_norm, "losses/skipped_update": float(not stepped),
                                       "losses/value_mean": float(values.mean()),
                                       "charts/lost_agents": float(window.lost_agents)})
                if cfg.checkpoint_every and p.timesteps >= p.next_checkpoint:
                    save_params({"actor": actor, "critic": critic}, run_dir / "checkpoints" / f"step_{p.timesteps}.npz")
                    p.next_checkpoint += cfg.checkpoint_every
        except KeyboardInterrupt:
            stop.taken()
            interrupted = True
            print(f"interrupted at {p.timesteps:,} steps; saving actor and critic", file=sys.stderr, flush=True)
        except Exception:
            save_on_crash(lambda path: save_params({"actor": actor, "critic": critic}, path), run_dir / "crash.npz", p.timesteps)
            raise
        log.close()
        final = save_params({"actor": actor, "critic": critic}, run_dir / "final.npz")
        result = TrainResult(run_dir, final, p.timesteps, interrupted, log.summary())
    finally:
        env.close()
    s = result.summary
    print(f"done: {result.timesteps:,} steps, success rate {s['success_rate']:.2f}, "
          f"mean return {s['mean_return']:.2f}; actor and critic {final}", flush=True)
    return result
