"""PPO on the tensor env, its rollout kept in tensors on the learner's device (``--algo ppo``).

SB3's PPO (``--algo sb3-ppo``) reaches the env through ``VecEnv.step``: numpy observations, one
info dict per agent, ``VecNormalize`` copying the whole observation dict (images included) every
step, and a numpy rollout buffer copied to torch for every minibatch. At 256 agents that is most
of the learner's time per step. Here, as in CleanRL's and LeanRL's PPO, the loop reads top to bottom
on :meth:`~visfly_dist.client.env_base.DroneEnvBase.step_tensor`:

1. **Act.** The policy (SB3's ``MultiInputActorCriticPolicy`` with our extractors, so checkpoints are
   SB3 ``.zip`` files that ``eval`` and ``export`` load as before) samples actions for the current,
   already normalised observation on the learner's device (on a GPU, replayed from a CUDA graph:
   :mod:`visfly_dist.training.graphed_policy`).
2. **Step.** ``step_tensor`` advances the agents and hands over its observation tensors (the images a
   view of the workers' shared-memory segment), rewards and end flags on the host.
3. **Normalise where they are, then one copy.** Vector entries (``state``, ``target``, ...) and
   rewards are scaled by running statistics kept beside the env (VecNormalize's formulas: clip 10,
   epsilon 1e-8, returns discounted by ``gamma``), one native call each
   (:mod:`~visfly_dist.training.native_kernels`): on a GPU the same arithmetic is some forty kernel
   launches a step for a few hundred numbers. Images are never copied for it. The normalised step
   then crosses to the device in one copy through pinned memory
   (:mod:`visfly_dist.training.device_stage`), into the preallocated rollout tensors
   (``observations[t]``, ``actions[t]``, ``log_probs[t]``, ``values[t]``, ``rewards[t]``, ``dones[t]``).
   A rollout of every agent at once keeps each step's images as the env handed them out (on a CPU,
   views of the workers' segments, which the env keeps for it: ``hold_observations``), not copied;
   a minibatch gathers its rows from them once. A truncated episode (time limit,
   scene swap, a worker away too long) is bootstrapped with the value of its terminal observation, as
   SB3 does. A step in which an agent was *held* (its worker failed and is being replaced: the env
   undid its step) is no transition: it is left out of the return statistics, GAE passes over it,
   and the update never samples it.
4. **Learn.** GAE on the device, then ``n_epochs`` passes of shuffled minibatches; on a CPU each
   minibatch is split across threads (:mod:`visfly_dist.training.parallel_update`, the thread
   count timed by :class:`~visfly_dist.training.threads.UpdateThreadChooser`).

With ``overlap`` (the host plan turns it on where there are cores for it) the agents are split in
two groups stepped through ``send``/``recv`` (Sample Factory's double-buffered sampling): while the
workers render one group, the learner takes in the other and runs the policy on it. Both groups
act on the same policy, so there is no policy lag.

A run writes what the SB3 trainer writes (``config.json``, TensorBoard and ``progress.csv``,
``success_curve.csv``/``.png``, ``checkpoints/step_<n>.zip`` and ``final.zip`` with ``*.norm.npz``).
"""

from __future__ import annotations

import ctypes
import itertools
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.utils import explained_variance

from visfly_dist.client.env_base import DroneEnvBase
from visfly_dist.client.frame import row_span
from visfly_dist.training.callbacks import SuccessCallback
from visfly_dist.training.checkpoints import save_normalization
from visfly_dist.training.device_stage import DeviceStage
from visfly_dist.training.graphed_policy import GraphedForward
from visfly_dist.training.native_kernels import addresses, load_kernels
from visfly_dist.training.parallel_update import UpdateSettings, mean_stats, minibatch_gradients
from visfly_dist.training.threads import UpdateThreadChooser

CLIP_OBS = 10.0
CLIP_REWARD = 10.0
EPSILON = 1e-8


class RunningMoments:
    """Running mean and variance of a batch stream (Chan et al.'s parallel update, as SB3's
    ``RunningMeanStd``), float64 tensors on ``device``."""

    def __init__(self, shape: tuple[int, ...], device: torch.device) -> None:
        self.mean = torch.zeros(shape, dtype=torch.float64, device=device)
        self.var = torch.ones(shape, dtype=torch.float64, device=device)
        self.count = 1e-4

    def update(self, batch: torch.Tensor) -> None:
        batch = batch.detach().to(torch.float64).reshape(-1, *self.mean.shape)
        n = batch.shape[0]
        if n == 0:
            return
        batch_var, batch_mean = torch.var_mean(batch, dim=0, correction=0)
        delta = batch_mean - self.mean
        total = self.count + n
        self.mean = self.mean + delta * (n / total)
        self.var = (self.var * self.count + batch_var * n + delta.square() * (self.count * n / total)) / total
        self.count = total

    def as_numpy(self) -> Any:
        """Mean, var and count as numpy values (the attributes ``save_normalization`` reads)."""
        return _Moments(self.mean.cpu().numpy(), self.var.cpu().numpy(), float(self.count))


@dataclass
class _Moments:
    """Mean, variance (arrays or tensors) and count of one entry's statistics."""

    mean: Any
    var: Any
    count: float

    def as_numpy(self) -> "_Moments":
        return _Moments(np.asarray(self.mean.cpu()), np.asarray(self.var.cpu()), self.count)


class Normalizer:
    """Observation and reward normalisation with VecNormalize's formulas and statistics (saved in the
    same ``*.norm.npz``, so ``eval`` rebuilds a ``VecNormalize`` from it), on the env's device.

    Args:
        space: the env's observation space; its float vector entries are normalised.
        num_envs: agents (one discounted return each).
        gamma: discount of the returns whose spread scales the rewards.
        device: where the statistics live.
        enabled: ``False`` passes observations and rewards through unchanged.
        native: on a CPU, a step's float32 observations and (none held) rewards are
            normalised in one call of the native kernels each (:mod:`~visfly_dist.training.native_kernels`,
            where built and not switched off) instead of about twenty torch operations: the same
            statistics up to the rounding of the batch moments, the same scaled values. ``False``:
            torch's operations always.
    """

    def __init__(self, space: spaces.Dict, num_envs: int, gamma: float, device: torch.device, enabled: bool = True,
                 native: bool = True) -> None:
        from visfly_dist.training.run import vector_keys

        self.keys = vector_keys(space) if enabled else []
        self.enabled = enabled
        self.gamma = gamma
        # every vector entry's features in one row: one statistics update and one normalisation a step
        self._shapes = {k: tuple(space.spaces[k].shape or ()) for k in self.keys}
        widths = [math.prod(shape) for shape in self._shapes.values()]
        self._columns = {k: slice(start, start + width)  # each entry's columns of the joint row
                         for k, start, width in zip(self.keys, itertools.accumulate([0] + widths), widths)}
        self._moments = RunningMoments((sum(widths),), device)
        self.ret_moments = RunningMoments((), device)
        self.returns = torch.zeros(num_envs, dtype=torch.float64, device=device)
        self._widths = (ctypes.c_int64 * len(widths))(*widths)
        self._kernels = load_kernels()[0] if native and torch.device(device).type == "cpu" else None

    @property
    def obs_moments(self) -> dict[str, "_Moments"]:
        """Each vector entry's statistics (views of the joint ones), as a ``VecNormalize`` keeps them."""
        m = self._moments
        return {k: _Moments(m.mean[self._columns[k]].reshape(shape), m.var[self._columns[k]].reshape(shape), float(m.count))
                for k, shape in self._shapes.items()}

    def observe(self, obs: dict[str, torch.Tensor], update: bool = True) -> dict[str, torch.Tensor]:
        """``obs`` with its vector entries normalised (after adding them to the statistics)."""
        if not self.keys:
            return obs
        if (lib := self._kernels) is not None:
            fast = self._observe_native(lib, obs, update)
            if fast is not None:
                return fast
        rows = next(iter(obs.values())).shape[0]
        joint = torch.cat([obs[k].reshape(rows, -1) for k in self.keys], dim=1)
        m = self._moments
        if update:
            m.update(joint)
        scaled = ((joint - m.mean) / torch.sqrt(m.var + EPSILON)).clamp(-CLIP_OBS, CLIP_OBS)
        out = dict(obs)
        for k, shape in self._shapes.items():
            out[k] = scaled[:, self._columns[k]].reshape((rows,) + shape).to(obs[k].dtype)
        return out

    def _observe_native(self, lib: ctypes.CDLL, obs: dict[str, torch.Tensor],
                        update: bool) -> dict[str, torch.Tensor] | None:
        """:meth:`observe` in one kernel call, or ``None`` where it does not take the entries
        (not float32 CPU tensors of this normaliser's shapes, or no rows)."""
        inputs = [obs[k] for k in self.keys]
        rows = inputs[0].shape[0]
        if rows == 0 or any(x.dtype != torch.float32 or not x.is_cpu or x.shape != (rows,) + shape
                            for x, shape in zip(inputs, self._shapes.values())):
            return None
        inputs = [x if x.is_contiguous() else x.contiguous() for x in inputs]
        outputs = [torch.empty(x.shape, dtype=torch.float32) for x in inputs]
        m = self._moments
        mean, var = (torch.empty_like(m.mean), torch.empty_like(m.var)) if update else (None, None)
        lib.vf_normalize_obs_f32(
            addresses(inputs), addresses(outputs), self._widths, len(inputs), rows, m.mean.data_ptr(), m.var.data_ptr(),
            None if mean is None else mean.data_ptr(), None if var is None else var.data_ptr(), m.count, EPSILON, CLIP_OBS)
        if mean is not None and var is not None:
            m.mean, m.var, m.count = mean, var, m.count + rows
        return {**obs, **dict(zip(self.keys, outputs))}

    def reward(self, reward: torch.Tensor, done: torch.Tensor, rows: torch.Tensor | None = None,
               held: torch.Tensor | None = None) -> torch.Tensor:
        """Scaled rewards of agents ``rows`` (default all); their discounted returns restart where
        ``done`` and stay as they are where ``held`` (a step that did not happen)."""
        if not self.enabled:
            return reward
        before = self.returns if rows is None else self.returns[rows]
        lib = self._kernels
        native = self._reward_native(lib, reward, done, before) if lib is not None and held is None else None
        if native is not None:
            scaled, returns = native
        else:
            returns = before * self.gamma + reward.to(torch.float64)
            if held is None:
                self.ret_moments.update(returns)
            else:
                returns = torch.where(held, before, returns)
                self.ret_moments.update(returns[~held])
            scaled = (reward / torch.sqrt(self.ret_moments.var + EPSILON).to(reward.dtype)).clamp(-CLIP_REWARD, CLIP_REWARD)
            returns = torch.where(done, 0.0, returns)
        if rows is None:
            self.returns = returns
        else:
            self.returns[rows] = returns
        return scaled

    def _reward_native(self, lib: ctypes.CDLL, reward: torch.Tensor, done: torch.Tensor,
                       before: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The scaled rewards and new returns of agents whose returns were ``before``, none held, in
        one kernel call (the return statistics updated), or ``None`` where it does not take them
        (not float32 rewards and bool ends on the CPU, one per agent)."""
        n = reward.shape[0]
        if (n == 0 or reward.dtype != torch.float32 or done.dtype != torch.bool or not reward.is_cpu or not done.is_cpu
                or reward.shape != before.shape or done.shape != before.shape):
            return None
        reward, done = reward.contiguous(), done.contiguous()
        m = self.ret_moments
        returns, mean, var = torch.empty_like(before), torch.empty_like(m.mean), torch.empty_like(m.var)
        scaled = torch.empty(n, dtype=torch.float32)
        lib.vf_normalize_reward_f32(
            reward.data_ptr(), done.data_ptr(), before.data_ptr(), returns.data_ptr(), n, self.gamma,
            m.mean.data_ptr(), m.var.data_ptr(), mean.data_ptr(), var.data_ptr(), m.count, EPSILON, CLIP_REWARD,
            scaled.data_ptr())
        m.mean, m.var, m.count = mean, var, m.count + n
        return scaled, returns

    def save(self, path: Path) -> None:
        """Write the statistics as ``save_normalization`` writes a VecNormalize's."""
        save_normalization(_Statistics(self), path)


class _Statistics:
    """The attributes of a ``VecNormalize`` that ``save_normalization`` reads, from a :class:`Normalizer`."""

    def __init__(self, norm: Normalizer) -> None:
        self.clip_obs, self.clip_reward, self.epsilon, self.gamma = CLIP_OBS, CLIP_REWARD, EPSILON, norm.gamma
        self.norm_reward = norm.enabled
        self.ret_rms = norm.ret_moments.as_numpy()
        self.obs_rms = {k: m.as_numpy() for k, m in norm.obs_moments.items()}


class Rollout:
    """Tensors of one rollout, ``(n_steps, num_envs, ...)``, allocated once on the learner's device.

    With ``kept_images`` (a rollout of every agent at once) each image entry is kept as the env
    handed it out, one ``(num_envs, C, H, W)`` tensor per step, never copied: the env never writes
    into an observation it handed out, and the tensors (views of the workers' segments on a CPU)
    are let go when the next rollout replaces them. A minibatch gathers its rows from them once.
    """

    def __init__(self, space: spaces.Dict, n_steps: int, num_envs: int, device: torch.device,
                 kept_images: bool = False) -> None:
        shape = (n_steps, num_envs)
        self.num_envs = num_envs
        images = {k for k, s in space.spaces.items() if kept_images and len(s.shape or ()) == 3}
        self.observations = {k: torch.zeros(shape + tuple(s.shape or ()), dtype=_torch_dtype(np.dtype(s.dtype)), device=device)
                             for k, s in space.spaces.items() if k not in images}
        self.images: dict[str, list[torch.Tensor]] = {k: [] for k in images}  # step t's at [t]
        self.actions = torch.zeros(shape + (4,), device=device)
        self.log_probs = torch.zeros(shape, device=device)
        self.values = torch.zeros(shape, device=device)
        self.rewards = torch.zeros(shape, device=device)
        self.dones = torch.zeros(shape, dtype=torch.bool, device=device)
        self.held = torch.zeros(shape, dtype=torch.bool, device=device)  # no transition: the agent was held
        self.advantages = torch.zeros(shape, device=device)
        self.returns = torch.zeros(shape, device=device)

    def store_observation(self, t: int, rows: slice | torch.Tensor, obs: dict[str, torch.Tensor]) -> None:
        """The observation acted on at step ``t`` by agents ``rows`` (all of them for a kept image)."""
        for k, v in obs.items():
            kept = self.images.get(k)
            if kept is None:
                self.observations[k][t, rows] = v
            elif t < len(kept):
                kept[t] = v
            else:
                kept.append(v)

    def gather_observations(self, idx: torch.Tensor) -> dict[str, torch.Tensor]:
        """The observations of the flat rows ``idx`` (``t * num_envs + agent``, ascending)."""
        out = {k: v.reshape(-1, *v.shape[2:])[idx] for k, v in self.observations.items()}
        if not self.images:
            return out
        steps = idx // self.num_envs
        counts = torch.bincount(steps, minlength=len(next(iter(self.images.values())))).tolist()
        for k, kept in self.images.items():
            rows = kept[0].new_empty((len(idx),) + kept[0].shape[1:])
            start = 0
            for t, count in enumerate(counts):
                if count:
                    agents = idx[start:start + count] - t * self.num_envs
                    torch.index_select(kept[t], 0, agents, out=rows[start:start + count])
                    start += count
            out[k] = rows
        return out

    def compute_gae(self, last_values: torch.Tensor, gamma: float, gae_lambda: float) -> None:
        """Advantages and returns (GAE); ``last_values``: values of the observations after the last step.
        A held step is passed over: the step before it bootstraps from the step after it."""
        next_value, running = last_values, torch.zeros_like(last_values)
        for t in reversed(range(self.rewards.shape[0])):
            live = (~self.dones[t]).float()
            delta = self.rewards[t] + gamma * next_value * live - self.values[t]
            step = delta + gamma * gae_lambda * live * running
            held = self.held[t]
            running = torch.where(held, running, step)
            self.advantages[t] = running
            next_value = torch.where(held, next_value, self.values[t])
        self.returns = self.advantages + self.values


@dataclass
class Minibatch:
    """The fields ``minibatch_gradients`` reads, for one minibatch of rows."""

    observations: dict[str, torch.Tensor]
    actions: torch.Tensor
    old_values: torch.Tensor
    old_log_prob: torch.Tensor
    advantages: torch.Tensor
    returns: torch.Tensor


def _torch_dtype(dtype: np.dtype) -> torch.dtype:
    return torch.from_numpy(np.zeros(0, dtype=dtype)).dtype


class TensorPPO:
    """PPO top to bottom on the tensor env (see the module docstring).

    Args:
        model: the SB3 ``PPO`` that holds the policy, its optimizer, the hyperparameters and the
            logger (its own rollout collection and update are not used).
        env: the task env (``step_tensor``, ``send``/``recv``).
        normalize: normalise vector observations and rewards.
        overlap: two groups of agents stepped in turn through ``send``/``recv``.
        update_threads: threads of a CPU update (``None``: timed choice between every CPU and one).
        cpu_cores: the cores of the update's threads (from the host plan).
    """

    def __init__(self, model: PPO, env: DroneEnvBase, normalize: bool = True, overlap: bool = False,
                 update_threads: int | None = None, cpu_cores: int = 1) -> None:
        self.model, self.env, self.policy = model, env, model.policy
        self.device = model.device
        self.n_steps, self.num_envs = model.n_steps, env.num_envs
        # on the env's side (the host): a step's vectors and rewards are small, and there one native call
        # each normalises them where a GPU took some forty kernel launches (2.7 ms a step at 256 agents)
        self.norm = Normalizer(env.observation_space, env.num_envs, model.gamma, env.device, enabled=normalize)
        self.groups = self._groups(overlap)
        self.rollout = Rollout(env.observation_space, self.n_steps, env.num_envs, self.device,
                               kept_images=len(self.groups) == 1)
        if self.rollout.images:
            env.hold_observations(self.n_steps + 1)  # the rollout's, and the one acted on next
        # each group's rows of the rollout: a slice (every row for one group; the halves are consecutive,
        # and a slice stores a group's images as one block), else its rows on the learner's device
        self.group_rows: list[slice | torch.Tensor] = (
            [slice(None)] if len(self.groups) == 1 else [row_span(ids) or ids.to(self.device) for ids in self.groups])
        self.stage = DeviceStage(self.device)  # a step's observation, rewards and flags: one copy to the device
        self.forward = GraphedForward(self.policy)  # the rollout's policy calls: CUDA graphs on a GPU
        if self.device.type == "cuda":  # the trunk's shapes are fixed: let cuDNN time its algorithms once
            torch.backends.cudnn.benchmark = True
        self.threads = UpdateThreadChooser([update_threads] if update_threads else [max(cpu_cores, 1), 1])
        self.phase_seconds = {"rollout_s": 0.0, "update_s": 0.0, "loop_s": 0.0}
        # each group's normalised observation, on the device: a group acts on its own, never gathered or scattered
        self._obs: list[dict[str, torch.Tensor]] | None = None
        self._on_episode: Callable[[dict[str, Any]], None] | None = None

    def _groups(self, overlap: bool) -> list[torch.Tensor]:
        """The agents' groups: everyone, or two halves of whole teams."""
        n, team = self.num_envs, max(self.env.agents_per_scene if self.env.config.multi_agent else 1, 1)
        teams = n // team
        if not overlap or teams < 2:
            return [torch.arange(n)]
        half = (teams // 2) * team
        return [torch.arange(0, half), torch.arange(half, n)]

    # ----- the loop ------------------------------------------------------------------------------

    def learn(self, total_timesteps: int, success: SuccessCallback, on_rollout_end: Callable[[int], None] | None = None) -> None:
        """Collect and update until ``total_timesteps`` env steps; ``success`` takes every finished
        episode and logs the curve; ``on_rollout_end(num_timesteps)`` runs after each rollout
        (checkpoints, videos)."""
        model = self.model
        success.init_callback(model)
        success.on_training_start(locals(), globals())
        self._on_episode = success.record_episode
        if self._obs is None:
            self.reset()
        t0 = time.perf_counter()
        try:
            while model.num_timesteps < total_timesteps:
                t1 = time.perf_counter()
                self.collect()
                t2 = time.perf_counter()
                self.phase_seconds["rollout_s"] += t2 - t1
                model.num_timesteps += self.n_steps * self.num_envs
                success.num_timesteps = model.num_timesteps
                success.on_rollout_end()
                if on_rollout_end is not None:
                    on_rollout_end(model.num_timesteps)
                self.update()
                self.phase_seconds["update_s"] += time.perf_counter() - t2
                model.logger.record("time/total_timesteps", model.num_timesteps, exclude="tensorboard")
                model.logger.dump(step=model.num_timesteps)
        finally:
            self.phase_seconds["loop_s"] += time.perf_counter() - t0
            success.on_training_end()

    def reset(self) -> None:
        """Reset the env and take in its first observation (``learn`` does this before its first rollout)."""
        first = {k: torch.as_tensor(v) for k, v in self.env.reset().items()}
        everyone = self._to_device(self.norm.observe(first))
        self._obs = [{k: v[rows] for k, v in everyone.items()} for rows in self.group_rows]

    def collect(self) -> None:
        """One rollout of ``n_steps`` per agent into :attr:`rollout` (GAE included)."""
        self.policy.set_training_mode(False)
        with torch.no_grad():
            if len(self.groups) == 1:
                for t in range(self.n_steps):
                    actions = self._act(0, t)
                    self._take(0, t, self.env.step_tensor(actions, terminal="ended"))
            else:
                self._collect_overlapped()
            last_values = self.policy.predict_values(self._observation()).flatten()
        self.rollout.compute_gae(last_values, self.model.gamma, self.model.gae_lambda)

    def _collect_overlapped(self) -> None:
        """Both groups in flight: take in whichever is rendered, act on it, send it again."""
        steps = [0] * len(self.groups)
        owner = torch.empty(self.num_envs, dtype=torch.long)
        for g, ids in enumerate(self.groups):
            owner[ids] = g
            self.env.send(self._act(g, 0), ids)
        in_flight = len(self.groups)
        while in_flight:
            result, ids = self.env.recv(terminal="ended")
            g = int(owner[int(ids[0])])
            self._take(g, steps[g], result)
            steps[g] += 1
            if steps[g] < self.n_steps:
                self.env.send(self._act(g, steps[g]), self.groups[g])
            else:
                in_flight -= 1

    def _act(self, g: int, t: int) -> torch.Tensor:
        """Sample actions for group ``g`` at rollout step ``t`` and store what PPO needs of them."""
        assert self._obs is not None, "learn() resets the env before it collects"
        obs = self._obs[g]
        actions, values, log_probs = self.forward(obs)
        r = self.rollout
        rows = self.group_rows[g]
        r.store_observation(t, rows, obs)
        r.actions[t, rows] = actions
        r.values[t, rows] = values.flatten()
        r.log_probs[t, rows] = log_probs
        return actions.clamp(-1.0, 1.0).to(self.env.device)

    def _take(self, g: int, t: int, result: Any) -> None:
        """Rewards, ends and next observations of group ``g`` from its step ``t``."""
        obs, reward, terminated, truncated, info = result
        everyone = len(self.groups) == 1
        ended, held = terminated | truncated, info["held"]
        # the env's flags are on the host: what to do is decided there, without waiting on the device
        any_held, any_cut, any_ended = bool(held.any()), bool(truncated.any()), bool(ended.any())
        # normalised where the env made them (one native call each on the host), then one copy to the device
        reward = self.norm.reward(reward.detach().to(torch.float32), ended, None if everyone else self.groups[g],
                                  held if any_held else None)
        if any_cut:  # bootstrap episodes that did not end by themselves (SB3's TimeLimit handling)
            cut_rows = truncated.nonzero().squeeze(1)  # on the env's device
            cut = truncated[ended]  # the terminal observation holds the ended rows only
            terminal = self.norm.observe({k: v[cut.to(v.device)] for k, v in info["terminal_observation"].items()},
                                         update=False)
        normalised = self.norm.observe(obs)
        moved = self.stage({**{f"obs.{k}": v for k, v in normalised.items()}, "reward": reward, "done": ended,
                            "held": held})
        reward, done, held = moved["reward"], moved["done"], moved["held"]
        if any_cut:
            reward = reward.clone()
            reward[cut_rows.to(self.device)] += self.model.gamma * self.policy.predict_values(
                self._to_device(terminal)).flatten()
        r = self.rollout
        index = self.group_rows[g]
        r.rewards[t, index] = reward
        r.dones[t, index] = done
        r.held[t, index] = held
        assert self._obs is not None, "learn() resets the env before it collects"
        self._obs[g] = {k: moved[f"obs.{k}"] for k in obs}
        if any_ended and self._on_episode is not None:  # a collect outside learn() records no episodes
            self._record_episodes(ended, truncated, info)

    def _record_episodes(self, done: torch.Tensor, truncated: torch.Tensor, info: dict[str, Any]) -> None:
        """Hand every finished episode's outcome to the episode log."""
        rows = done.nonzero().squeeze(1)
        success, collision, out_of_bounds, lost, swapped, cut = torch.stack(
            [info[k] for k in ("success", "collision", "out_of_bounds", "lost", "swapped")] + [truncated]
        ).index_select(1, rows).tolist()  # one gather and one copy to Python for the six flags
        returns = info["episode_return"].index_select(0, rows).tolist()
        lengths = info["episode_length"].index_select(0, rows).tolist()
        for j in range(len(returns)):
            assert self._on_episode is not None  # _take records only with a callback
            self._on_episode({"is_success": success[j], "collision": collision[j], "out_of_bounds": out_of_bounds[j],
                              "lost": lost[j], "swapped": swapped[j], "TimeLimit.truncated": cut[j],
                              "episode": {"r": float(returns[j]), "l": int(lengths[j])}})

    def _observation(self) -> dict[str, torch.Tensor]:
        """The normalised observation of every agent, on the device (there once ``learn`` reset the env)."""
        assert self._obs is not None, "learn() resets the env before it collects"
        if len(self._obs) == 1:
            return self._obs[0]
        first = self._obs[0]
        out = {k: torch.empty((self.num_envs, *v.shape[1:]), dtype=v.dtype, device=v.device) for k, v in first.items()}
        for rows, obs in zip(self.group_rows, self._obs):
            for k, v in obs.items():
                out[k][rows] = v
        return out

    def _to_device(self, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        if self.device.type == "cpu":
            return {k: v.detach() for k, v in obs.items()}
        return {k: v.detach().to(self.device, non_blocking=True) for k, v in obs.items()}

    # ----- the update ----------------------------------------------------------------------------

    def update(self) -> None:
        """``n_epochs`` passes of shuffled minibatches over the rollout (SB3's PPO loss and logs)."""
        model, policy, r = self.model, self.policy, self.rollout
        policy.set_training_mode(True)
        size = self.n_steps * self.num_envs
        transitions = (~r.held).reshape(size).nonzero().squeeze(1)  # held steps are not sampled
        if len(transitions) == 0:  # every agent was held for the whole rollout: nothing to learn from
            return
        actions, values, log_probs = r.actions.reshape(size, -1), r.values.reshape(size), r.log_probs.reshape(size)
        advantages, returns = r.advantages.reshape(size), r.returns.reshape(size)
        clip = model.clip_range  # a schedule once SB3 set the model up
        settings = UpdateSettings(clip_range=float(clip(1.0) if callable(clip) else clip), clip_range_vf=None,
                                  ent_coef=float(model.ent_coef), vf_coef=float(model.vf_coef),
                                  normalize_advantage=model.normalize_advantage)
        on_cpu = self.device.type == "cpu"
        shards = self.threads.next() if on_cpu else 1
        rollout_threads = torch.get_num_threads()
        if on_cpu:
            torch.set_num_threads(1)
        pool = ThreadPoolExecutor(max_workers=shards - 1, thread_name_prefix="ppo-shard") if shards > 1 else None
        stats, t0 = [], time.perf_counter()
        try:
            for _ in range(model.n_epochs):
                order = transitions[torch.randperm(len(transitions), device=self.device)]
                for start in range(0, len(order), model.batch_size):
                    idx = order[start:start + model.batch_size].sort().values  # step by step: one gather per step
                    batch = Minibatch(r.gather_observations(idx), actions[idx], values[idx],
                                      log_probs[idx], advantages[idx], returns[idx])
                    policy.optimizer.zero_grad()
                    stats.append(minibatch_gradients(policy, batch, settings, False, pool, shards))
                    torch.nn.utils.clip_grad_norm_(policy.parameters(), model.max_grad_norm)
                    policy.optimizer.step()
                model._n_updates += 1
            self.forward.verify()  # CUDA graphs still agree with the updated policy (else: eager)
        finally:
            if pool is not None:
                pool.shutdown(wait=True)
            torch.set_num_threads(rollout_threads)
            if on_cpu:
                self.threads.record(shards, time.perf_counter() - t0)
        record, means = model.logger.record, mean_stats(stats)
        record("train/update_threads", shards)
        record("train/entropy_loss", means["entropy_loss"])
        record("train/policy_gradient_loss", means["policy_loss"])
        record("train/value_loss", means["value_loss"])
        record("train/approx_kl", means["approx_kl"])
        record("train/clip_fraction", means["clipped"])
        record("train/explained_variance", float(explained_variance(values[transitions].cpu().numpy(),
                                                                    returns[transitions].cpu().numpy())))
        record("train/held_steps", size - len(transitions))
        record("train/std", float(torch.exp(policy.log_std.detach()).mean()))
        record("train/n_updates", model._n_updates, exclude="tensorboard")

    def save(self, path: Path) -> Path:
        """The policy as an SB3 ``.zip`` and the normalisation statistics beside it."""
        from visfly_dist.training.checkpoints import norm_path

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.model.save(path)
        if self.norm.enabled:
            self.norm.save(norm_path(path))
        return path
