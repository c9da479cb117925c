"""PPO whose next rollout is collected while it learns from the last one (policy lag of one update).

Plain PPO alternates: the scene workers sit idle while the learner updates, and the learner waits
while the workers render. :class:`OverlappedPPO` keeps both busy, as asynchronous PPO (APPO) does:

    rollout k (policy k-1 snapshot) ──────▶ update k (on rollout k)
                                            rollout k+1 (snapshot of policy k, background thread)
                                                      ──────▶ update k+1 (on rollout k+1) ...

When an update starts, a frozen copy of the current policy (the *behaviour* policy) starts
collecting the next rollout in a background thread, into a second buffer, while the update runs.
The next update waits for that rollout and learns from it; the lag is exactly one update
(``train/policy_lag_updates``). Torch releases the GIL inside its kernels and the env waits on the
workers without the GIL, so the two threads overlap.

The lag is corrected with decoupled PPO (Hilton et al., 2022, "Batch size-invariance for policy
optimization"): plain PPO would clip the ratio to the behaviour policy, which is already one update
away from the policy being trained, so the first epoch starts with clipped samples and learns less
per sample. Before each update on a lagged rollout, the log-probabilities of its actions are
recomputed under the current policy (the *proximal* policy, one forward pass), PPO clips around
those, and each sample's advantage is weighted by ``pi_prox / pi_behaviour`` (truncated at
:data:`IMPORTANCE_CLIP`), which keeps the objective's gradient that of the behaviour data
(``train/importance_weight_mean``).

Callbacks and episode statistics are replayed on the main thread when the rollout is taken in, so
they see the same ``infos``/``dones`` sequence as with SB3's own ``collect_rollouts``.

Attributes:
    phase_seconds: ``rollout_s`` (collection, wherever it ran), ``update_s`` (gradient steps),
        ``wait_s`` (the learner waiting for a rollout) since construction.
"""

from __future__ import annotations

import os
import threading
import time
from typing import Any, cast

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.utils import obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv

from visfly_dist.training.parallel_update import sharded_ppo_train
from visfly_dist.training.threads import UpdateThreadChooser

IMPORTANCE_CLIP = 2.0
"""Truncation of the proximal/behaviour importance weights of a lagged rollout (as V-trace truncates)."""
PROXIMAL_CHUNK = 512
"""Samples per forward pass when the proximal log-probabilities are recomputed."""


class UpdateThreadsPPO(PPO):
    """Plain SB3 PPO whose update may use more threads (the scene workers are idle then), and
    reports its phase times.

    :meth:`train` splits each minibatch across ``update_threads`` threads, each running its part's
    forward and backward pass on one torch thread (:func:`~visfly_dist.training.parallel_update.sharded_ppo_train`:
    the same update as SB3's, with one meeting point per minibatch instead of one per operator).
    With ``update_threads=None`` it uses every CPU this process may use or one thread, whichever the
    updates so far ran faster with (:class:`~visfly_dist.training.threads.UpdateThreadChooser`;
    logged as ``train/update_threads``). During rollouts torch stays at the thread count it was
    given (one, so it does not fight the local workers for the cores).
    """

    def __init__(self, *args: Any, update_threads: int | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.update_threads = update_threads
        self.thread_chooser = UpdateThreadChooser([update_threads] if update_threads
                                                  else [len(os.sched_getaffinity(0)), 1])
        self.phase_seconds = {"rollout_s": 0.0, "update_s": 0.0}

    def _excluded_save_params(self) -> list[str]:
        return super()._excluded_save_params() + ["phase_seconds", "thread_chooser"]

    def collect_rollouts(self, *args: Any, **kwargs: Any) -> bool:
        t0 = time.perf_counter()
        try:
            return super().collect_rollouts(*args, **kwargs)
        finally:
            self.phase_seconds["rollout_s"] += time.perf_counter() - t0

    def train(self) -> None:
        rollout_threads = torch.get_num_threads()
        threads = self.thread_chooser.next()
        on_cpu = self.device.type == "cpu"
        torch.set_num_threads(1 if on_cpu else rollout_threads)
        self.logger.record("train/update_threads", threads)
        t0 = time.perf_counter()
        try:
            sharded_ppo_train(self, threads if on_cpu else 1)
        finally:
            torch.set_num_threads(rollout_threads)
            seconds = time.perf_counter() - t0
            self.thread_chooser.record(threads, seconds)
            self.phase_seconds["update_s"] += seconds


class OverlappedPPO(PPO):
    """SB3 PPO with rollout collection overlapped with the update (see the module docstring)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.phase_seconds = {"rollout_s": 0.0, "update_s": 0.0, "wait_s": 0.0}
        self._next_buffer: RolloutBuffer | None = None
        self._worker: threading.Thread | None = None
        self._collected: dict[str, Any] | None = None
        self._behaviour: Any = None  # the frozen copy of the policy that collects the next rollout
        self._lagged = False  # whether self.rollout_buffer was collected by an older policy

    def _excluded_save_params(self) -> list[str]:
        return super()._excluded_save_params() + ["_next_buffer", "_worker", "_collected", "_behaviour", "_lagged",
                                                  "phase_seconds"]

    # ----- the two phases ---------------------------------------------------------------------

    def collect_rollouts(self, env: VecEnv, callback: BaseCallback, rollout_buffer: RolloutBuffer,
                         n_rollout_steps: int) -> bool:
        """Take in the rollout collected during the last update, or collect one now (the first)."""
        if self._worker is None:
            t0 = time.perf_counter()
            ok = super().collect_rollouts(env, callback, rollout_buffer, n_rollout_steps)
            self.phase_seconds["rollout_s"] += time.perf_counter() - t0
            return ok
        t0 = time.perf_counter()
        self._worker.join()
        self.phase_seconds["wait_s"] += time.perf_counter() - t0
        self._worker = None
        collected, self._collected = self._collected, None
        assert collected is not None and self._next_buffer is not None  # both set with the worker
        if "error" in collected:
            raise collected["error"]
        self.rollout_buffer, self._next_buffer = self._next_buffer, self.rollout_buffer
        self._lagged = True
        self._last_obs = collected["last_obs"]
        self._last_episode_starts = collected["episode_starts"]
        self.phase_seconds["rollout_s"] += collected["seconds"]
        return self._replay(callback, collected["steps"])

    def train(self) -> None:
        """Start collecting the next rollout with a snapshot of the policy, then update."""
        remaining = self._total_timesteps - self.num_timesteps
        if remaining > 0:
            self._start_collection()
        t0 = time.perf_counter()
        if self._lagged:
            weights = decouple_lagged_rollout(self.policy, self.rollout_buffer)
            self.logger.record("train/importance_weight_mean", float(weights.mean()))
            self._lagged = False
        super().train()
        self.phase_seconds["update_s"] += time.perf_counter() - t0
        self.logger.record("train/policy_lag_updates", 1 if remaining > 0 else 0)

    def learn(self, *args: Any, **kwargs: Any) -> "OverlappedPPO":
        try:
            return super().learn(*args, **kwargs)
        finally:
            self.join()

    def join(self) -> None:
        """Wait for a background collection still running (end of training, or an error)."""
        if self._worker is not None:
            self._worker.join()
            self._worker = None

    # ----- background collection ----------------------------------------------------------------

    def _start_collection(self) -> None:
        if self._next_buffer is None:
            self._next_buffer = type(self.rollout_buffer)(self.n_steps, self.observation_space, self.action_space, device=self.device,
                                             gamma=self.gamma, gae_lambda=self.gae_lambda, n_envs=self.n_envs)
        if self._behaviour is None:
            self._behaviour = self.policy_class(self.observation_space, self.action_space, self.lr_schedule,
                                                use_sde=self.use_sde, **self.policy_kwargs).to(self.device)
            self._behaviour.set_training_mode(False)
        self._behaviour.load_state_dict(self.policy.state_dict())
        self._worker = threading.Thread(target=self._collect, args=(self._behaviour, self._next_buffer),
                                        name="rollout", daemon=True)
        self._worker.start()

    def _collect(self, policy: Any, buffer: RolloutBuffer) -> None:
        """SB3's rollout loop with ``policy``, recording infos for the main thread to replay."""
        t0 = time.perf_counter()
        try:
            env, action_space = self.env, self.action_space
            obs, episode_starts = self._last_obs, self._last_episode_starts
            # learn() set the env and the first observation; the drones' actions are a Box
            assert env is not None and obs is not None and episode_starts is not None
            assert isinstance(action_space, spaces.Box)
            buffer.reset()
            steps = []
            dones = episode_starts
            for _ in range(self.n_steps):
                with torch.no_grad():
                    actions, values, log_probs = policy(obs_as_tensor(obs, self.device))
                actions = actions.cpu().numpy()
                clipped = np.clip(actions, action_space.low, action_space.high)
                new_obs, rewards, dones, infos = env.step(clipped)
                assert not isinstance(new_obs, tuple)  # SB3's buffers take an array or a dict
                for idx, done in enumerate(dones):  # bootstrap truncated episodes, as SB3 does
                    if done and infos[idx].get("terminal_observation") is not None \
                            and infos[idx].get("TimeLimit.truncated", False):
                        terminal = policy.obs_to_tensor(infos[idx]["terminal_observation"])[0]
                        with torch.no_grad():
                            rewards[idx] += self.gamma * policy.predict_values(terminal)[0].item()
                # RolloutBuffer.add is typed for arrays; the DictRolloutBuffer of a Dict space takes the dict
                buffer.add(cast(np.ndarray, obs), actions.reshape(-1, *action_space.shape), rewards, episode_starts, values,
                           log_probs)
                steps.append((infos, dones, rewards))
                obs, episode_starts = new_obs, dones
            with torch.no_grad():
                last_values = policy.predict_values(obs_as_tensor(obs, self.device))
            buffer.compute_returns_and_advantage(last_values=last_values, dones=dones)
            self._collected = {"last_obs": obs, "episode_starts": episode_starts, "steps": steps,
                               "seconds": time.perf_counter() - t0}
        except BaseException as exc:  # re-raised on the main thread
            self._collected = {"error": exc}

    def _replay(self, callback: BaseCallback, steps: list[tuple[list[dict], np.ndarray, np.ndarray]]) -> bool:
        """Feed the recorded steps to the callbacks and episode statistics, in order."""
        callback.on_rollout_start()
        for infos, dones, rewards in steps:
            self.num_timesteps += self.n_envs
            callback.update_locals({"infos": infos, "dones": dones, "rewards": rewards})
            if not callback.on_step():
                return False
            self._update_info_buffer(infos, dones)
        callback.on_rollout_end()
        return True


def decouple_lagged_rollout(policy: Any, buffer: RolloutBuffer) -> np.ndarray:
    """Turn ``buffer`` (collected by an older policy, before ``buffer.get``) into a decoupled-PPO batch.

    The stored log-probabilities become the current (proximal) policy's, so PPO's ratio is clipped
    around it, and each advantage is multiplied by ``min(pi_prox / pi_behaviour, IMPORTANCE_CLIP)``.
    Returns the weights, ``(n_steps, n_envs)``.
    """
    proximal = np.empty_like(buffer.log_probs)
    steps = max(1, PROXIMAL_CHUNK // buffer.n_envs)
    with torch.no_grad():
        for start in range(0, buffer.buffer_size, steps):
            rows = slice(start, start + steps)
            obs: torch.Tensor | dict[str, torch.Tensor]
            if isinstance(buffer.observations, dict):
                obs = {k: _flat_tensor(v[rows], policy.device) for k, v in buffer.observations.items()}
            else:
                obs = _flat_tensor(buffer.observations[rows], policy.device)
            _, log_prob, _ = policy.evaluate_actions(obs, _flat_tensor(buffer.actions[rows], policy.device))
            proximal[rows] = log_prob.cpu().numpy().reshape(proximal[rows].shape)
    weights = np.minimum(np.exp(proximal - buffer.log_probs), IMPORTANCE_CLIP).astype(buffer.advantages.dtype)
    buffer.advantages *= weights
    buffer.log_probs[:] = proximal
    return weights


def _flat_tensor(array: np.ndarray, device: Any) -> torch.Tensor:
    """``(steps, n_envs, ...)`` -> a ``(steps * n_envs, ...)`` tensor (the layout ``buffer.get`` yields)."""
    return torch.as_tensor(array.reshape(-1, *array.shape[2:]), device=device)
