"""What BPTT and SHAC share: the deterministic actor, the critic, the differentiable window rollout,
episode logging and parameter files (npz, no pickle).

The rollout keeps gradients through the env's batched dynamics and rewards
(``make_env(..., requires_grad=True)``): images are constants, agents reset inside a window start
from a fresh state (``torch.where``), so their gradient is cut at the reset, and the discount
restarts at 1 for their new episode.
"""

from __future__ import annotations

import csv
import sys
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np
import torch
from gymnasium import spaces
from torch import nn

from visfly_dist.errors import ConfigError
from visfly_dist.training.callbacks import CURVE_FIELDS, plot_success_curve
from visfly_dist.training.extractors import VisflyExtractor

MAX_GRAD_NORM = 1.0
"""Gradient clipping of the actor and the critic (global L2 norm)."""

HIDDEN = (64, 64)

Obs = dict[str, torch.Tensor]


def head(in_dim: int, out_dim: int, hidden: tuple[int, ...] = HIDDEN) -> nn.Sequential:
    """An MLP ``in_dim -> hidden (ELU) -> out_dim``."""
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [nn.Linear(in_dim, width), nn.ELU()]
        in_dim = width
    return nn.Sequential(*layers, nn.Linear(in_dim, out_dim))


class DiffActor(nn.Module):
    """Deterministic policy ``tanh(head(features(obs)))`` in ``[-1, 1]^4``.

    Args:
        observation_space: the env's Dict space (builds a :class:`VisflyExtractor` when ``extractor``
            is None).
        backbone: image backbone of the extractor.
        extractor: any module mapping an observation dict to ``(N, features_dim)``.
        features_dim: its output width (needed with ``extractor``).
    """

    def __init__(self, observation_space: spaces.Dict, backbone: str = "visfly-cnn",
                 extractor: Optional[nn.Module] = None, features_dim: Optional[int] = None) -> None:
        super().__init__()
        if extractor is None:
            extractor = VisflyExtractor(observation_space, backbone)
            features_dim = extractor.features_dim
        if features_dim is None:
            raise ConfigError("DiffActor(extractor=...) needs features_dim, the extractor's output width")
        self.extractor = extractor
        self.head = head(features_dim, 4)

    def forward(self, obs: Obs) -> torch.Tensor:
        return torch.tanh(self.head(self.extractor(obs)))

    def predict(self, obs: dict[str, np.ndarray], deterministic: bool = True) -> tuple[np.ndarray, None]:
        """SB3-style ``predict`` on numpy observations (for :func:`visfly_dist.training.evaluation.evaluate`)."""
        device = next(self.parameters()).device
        with torch.no_grad():
            action = self({k: torch.as_tensor(v, device=device) for k, v in obs.items()})
        return action.cpu().numpy().astype(np.float32), None


class Critic(nn.Module):
    """State value ``V(obs) = mean + std * head(features(obs))``; returns ``(N,)``.

    The network predicts values normalised by the running mean and standard deviation of the
    targets it was fitted to (:meth:`update_scale`): returns of tens reach the output at once,
    where an unnormalised head, moved by about ``lr`` per Adam step, needs thousands of steps.
    """

    mean: torch.Tensor
    var: torch.Tensor
    count: torch.Tensor

    def __init__(self, observation_space: spaces.Dict, backbone: str = "visfly-cnn") -> None:
        super().__init__()
        self.extractor = VisflyExtractor(observation_space, backbone)
        self.head = head(self.extractor.features_dim, 1)
        self.register_buffer("mean", torch.zeros(()))
        self.register_buffer("var", torch.ones(()))
        self.register_buffer("count", torch.zeros(()))

    def normalized(self, obs: Obs) -> torch.Tensor:
        """``(N,)`` the head's output: the value in units of the target scale."""
        return self.head(self.extractor(obs)).squeeze(-1)

    def forward(self, obs: Obs) -> torch.Tensor:
        return self.mean + self.var.sqrt() * self.normalized(obs)

    def normalize(self, values: torch.Tensor) -> torch.Tensor:
        """``values`` in the head's units."""
        return (values - self.mean) / self.var.sqrt()

    @torch.no_grad()
    def update_scale(self, targets: torch.Tensor) -> None:
        """Fold a batch of value targets into the running mean and variance (parallel Welford)."""
        n, mean, var = targets.numel(), targets.mean(), targets.var(unbiased=False)
        total = self.count + n
        delta = mean - self.mean
        self.var.copy_(((self.var * self.count + var * n + delta.square() * self.count * n / total) / total)
                       .clamp_min(1e-4))
        self.mean.add_(delta * n / total)
        self.count.copy_(total)


@dataclass
class Window:
    """One differentiable rollout of up to ``horizon`` steps (see :func:`rollout_window`).

    Attributes:
        loss: ``-sum_t gamma^t r_t`` (plus the bootstraps) summed over agents, divided by
            ``steps * N``; carries the graph back to the actor's parameters.
        steps: env steps taken (fewer than the horizon when a worker was lost).
        obs: the (detached) observations acted on, one dict per step.
        rewards: ``(steps, N)`` detached rewards (0 for lost agents).
        done: ``(steps, N)`` bool, the episode ended at this step (terminated, truncated or lost).
        next_values: ``(steps, N)`` detached bootstrap values after each step (0 on termination).
        valid: ``(steps, N)`` bool, the agent's step is real data (false where its worker was lost).
        next_obs: the observation after the last step (with its graph: detach before reuse).
        lost_agents: agents reported lost at the last step (0 unless the window was truncated).
        episodes: ``(success, return, length)`` of episodes that ended in this window.
    """

    loss: torch.Tensor
    steps: int
    obs: list[Obs]
    rewards: torch.Tensor
    done: torch.Tensor
    next_values: torch.Tensor
    valid: torch.Tensor
    next_obs: Obs
    lost_agents: int = 0
    episodes: list[tuple[float, float, float]] = field(default_factory=list)


def detach_obs(obs: Obs) -> Obs:
    return {k: v.detach() for k, v in obs.items()}


def rollout_window(env: Any, actor: Callable[[Obs], torch.Tensor], obs: Obs, horizon: int, gamma: float,
                   value: Optional[Callable[[Obs], torch.Tensor]] = None) -> Window:
    """Step ``env`` (anything with ``step_tensor`` and ``num_envs``) up to ``horizon`` times with gradients.

    The per-agent objective is ``sum_t d_t r_t`` with ``d_t = gamma^(t - t0)``, ``t0`` the start of
    the agent's current episode (the discount restarts at 1 after a done). With ``value`` (SHAC), an
    episode truncated inside the window adds ``d_t gamma V(terminal obs)`` and every agent still
    running at the end adds ``d_T V(obs_T)``; a terminated episode adds nothing.

    A lost or held agent (its worker died: the env holds it, then truncates it if the worker stays
    away) contributes no reward and no bootstrap at that step, and the window ends there: the caller
    logs it.
    """
    n = env.num_envs
    discount = obs_dtype_ones(obs, n)
    total = torch.zeros_like(discount)
    record_obs: list[Obs] = []
    rewards: list[torch.Tensor] = []
    dones: list[torch.Tensor] = []
    next_values: list[torch.Tensor] = []
    valids: list[torch.Tensor] = []
    episodes: list[tuple[float, float, float]] = []
    lost_agents = 0
    done = torch.zeros(n, dtype=torch.bool, device=discount.device)
    for _ in range(horizon):
        record_obs.append(detach_obs(obs))
        obs, reward, terminated, truncated, info = env.step_tensor(actor(obs))
        valid = ~(info["lost"] | info["held"])
        reward = torch.where(valid, reward, torch.zeros_like(reward))
        total = total + discount * reward
        done = terminated | truncated | ~valid
        boot = torch.zeros_like(total)
        if value is not None and bool((truncated & valid).any()):
            boot = torch.where(truncated & valid, value(info["terminal_observation"]), boot)
            total = total + discount * gamma * boot
        discount = torch.where(done, torch.ones_like(discount), discount * gamma)
        rewards.append(reward.detach())
        dones.append(done)
        next_values.append(boot.detach())
        valids.append(valid)
        ended = (done & valid).nonzero().flatten()
        if len(ended):
            episodes += zip(info["success"][ended].float().tolist(), info["episode_return"][ended].tolist(),
                            info["episode_length"][ended].float().tolist())
        lost_agents = int((~valid).sum())
        if lost_agents:
            break
    if value is not None:
        last = value(obs)
        total = total + torch.where(done, torch.zeros_like(last), discount * last)
        next_values[-1] = torch.where(done, next_values[-1], last.detach())
    steps = len(rewards)
    return Window(loss=-total.sum() / (steps * n), steps=steps, obs=record_obs, rewards=torch.stack(rewards),
                  done=torch.stack(dones), next_values=torch.stack(next_values), valid=torch.stack(valids),
                  next_obs=obs, lost_agents=lost_agents, episodes=episodes)


def obs_dtype_ones(obs: Obs, n: int) -> torch.Tensor:
    """``(n,)`` ones in the dtype and device of the first floating observation entry."""
    ref = next((v for v in obs.values() if v.is_floating_point()), None)
    if ref is None:
        return torch.ones(n)
    return torch.ones(n, dtype=ref.dtype, device=ref.device)


def decay_lr(optimizer: torch.optim.Optimizer, lr: float, done: int, total: int) -> None:
    """Linear learning-rate decay: ``lr`` at the start, ``lr / 10`` once ``done`` reaches ``total``."""
    for group in optimizer.param_groups:
        group["lr"] = lr * (1 - 0.9 * min(done / total, 1.0))


def clip_and_step(optimizer: torch.optim.Optimizer, params: list[nn.Parameter]) -> tuple[float, bool]:
    """Clip the gradient to ``MAX_GRAD_NORM`` and step; a non-finite gradient skips the step.

    Returns:
        The gradient norm before clipping, and whether the step was taken.
    """
    norm = float(nn.utils.clip_grad_norm_(params, MAX_GRAD_NORM))
    if not np.isfinite(norm):
        optimizer.zero_grad(set_to_none=True)
        return norm, False
    optimizer.step()
    return norm, True


class EpisodeLog:
    """Success rate, returns and lengths over the last ``window`` episodes; the success curve.

    Writes ``success_curve.csv`` (the PPO run's columns) and, at :meth:`close`, ``success_curve.png``;
    records ``charts/*`` into an SB3 logger (TensorBoard and ``progress.csv``) and prints progress.
    """

    def __init__(self, run_dir: Path, total_timesteps: int, logger: Any, window: int = 100,
                 print_every_s: float = 5.0, verbose: bool = True) -> None:
        self.run_dir = Path(run_dir)
        self.total = total_timesteps
        self.logger = logger
        self.episodes: deque[tuple[float, float, float]] = deque(maxlen=window)
        self.episodes_total = 0
        self.print_every_s = print_every_s
        self.verbose = verbose
        self.csv_path = self.run_dir / "success_curve.csv"
        with self.csv_path.open("w", newline="") as f:
            csv.writer(f).writerow(CURVE_FIELDS)
        self._t0 = time.perf_counter()
        self._last_print = 0.0

    def add(self, episodes: list[tuple[float, float, float]]) -> None:
        self.episodes.extend(episodes)
        self.episodes_total += len(episodes)

    def summary(self) -> dict[str, float]:
        """Success rate, mean return and mean length over the window (NaN before any episode)."""
        if not self.episodes:
            return dict(success_rate=float("nan"), mean_return=float("nan"), mean_length=float("nan"))
        arr = np.asarray(self.episodes)
        return dict(success_rate=float(arr[:, 0].mean()), mean_return=float(arr[:, 1].mean()),
                    mean_length=float(arr[:, 2].mean()))

    def dump(self, timesteps: int, extra: dict[str, float]) -> None:
        """Record ``extra`` (``losses/...``) and the charts at ``timesteps``; a curve row when episodes exist."""
        elapsed = time.perf_counter() - self._t0
        sps = timesteps / max(elapsed, 1e-9)
        for key, value in extra.items():
            self.logger.record(key, value)
        self.logger.record("charts/steps_per_second", sps)
        self.logger.record("time/total_timesteps", timesteps)
        self.logger.record("time/time_elapsed", elapsed)
        if self.episodes:
            s = self.summary()
            for key, value in s.items():
                self.logger.record(f"charts/{key}", value)
            with self.csv_path.open("a", newline="") as f:
                csv.writer(f).writerow((timesteps, f"{s['success_rate']:.4f}", f"{s['mean_return']:.4f}",
                                        f"{s['mean_length']:.1f}", self.episodes_total))
            now = time.perf_counter()
            if self.verbose and now - self._last_print >= self.print_every_s:
                self._last_print = now
                eta = (self.total - timesteps) / max(sps, 1e-9)
                print(f"[{timesteps:>9,}/{self.total:,}] {sps:6.0f} steps/s  success {s['success_rate']:.2f}  "
                      f"return {s['mean_return']:8.2f}  length {s['mean_length']:6.1f}  "
                      f"episodes {self.episodes_total}  eta {eta / 60:5.1f} min", flush=True, file=sys.stdout)
        self.logger.dump(timesteps)

    def close(self) -> None:
        plot_success_curve(self.csv_path, self.run_dir / "success_curve.png", self.episodes.maxlen or 0)


def save_params(modules: dict[str, nn.Module], path: Path) -> Path:
    """Write the parameters and buffers of ``modules`` to ``path`` (npz, keys ``NAME/param``; no pickle)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {f"{name}/{k}": v.detach().cpu().numpy() for name, m in modules.items() for k, v in m.state_dict().items()}
    with path.open("wb") as f:
        np.savez(f, **arrays)
    return path


def load_params(modules: dict[str, nn.Module], path: Path) -> None:
    """Load what :func:`save_params` wrote into ``modules`` (every module must be in the file).

    Raises:
        ConfigError: a missing file, or entries that do not fit the modules.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"checkpoint {str(path)!r} does not exist; pass a .npz written by 'visfly-dist train --algo bptt|shac'")
    with np.load(path, allow_pickle=False) as data:
        for name, module in modules.items():
            prefix = f"{name}/"
            state = {k[len(prefix):]: torch.as_tensor(data[k]) for k in data.files if k.startswith(prefix)}
            try:
                module.load_state_dict(state)
            except RuntimeError as exc:
                raise ConfigError(f"checkpoint {path} does not fit this {name} ({exc}); load it with the "
                                  "training's task and settings") from exc
