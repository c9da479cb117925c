"""PPO whose rollout steps two halves of the agents in turn, so learner and scene workers work at once.

SB3's rollout loop is a relay: the learner computes every agent's action, then waits while the
workers render, then the workers wait while the learner takes the step in and computes the next
actions. :class:`PipelinedPPO` splits the agents into two groups and keeps one group on the wire
while the learner handles the other::

    learner:  act A | act B | take A, act A | take B, act B | take A, act A | ...
    workers:          render A  | render B        | render A        | render B ...

It is the same on-policy PPO: every action comes from the current policy and the observation just
taken in (no policy lag, unlike ``--overlap``), and the rollout buffer receives the same columns as
with SB3's loop; only the time at which each group is stepped changes. The groups split each
worker's scenes in half, so every worker has work from both groups, and they hold whole teams in
team tasks. ``VecMonitor`` and ``VecNormalize`` are applied per group (their running statistics
see the same rows, in two batches per step).

It falls back to SB3's loop (with the reason logged once) when the env chain is not a visfly-dist
env under optional ``VecNormalize``/``VecMonitor`` wrappers, or the agents cannot be split.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.utils import obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv, VecMonitor, VecNormalize

from visfly_dist.client.env_base import DroneEnvBase
from visfly_dist.training.overlap import UpdateThreadsPPO


def agent_groups(assignment: dict[int, str | None], agents_per_scene: int, groups: int = 2) -> list[np.ndarray]:
    """Split the agents into ``groups`` groups of whole scenes, each worker's scenes dealt out in turn.

    Args:
        assignment: scene slot -> worker id (``None``: not placed yet).
        agents_per_scene: agents of each slot (slot ``s`` holds agents ``s * k ... s * k + k - 1``).
        groups: how many groups.

    Returns:
        Sorted agent index arrays, empty groups left out (one scene gives one group).
    """
    by_worker: dict[str, list[int]] = {}
    for slot in sorted(assignment):
        by_worker.setdefault(str(assignment[slot]), []).append(slot)
    members: list[list[int]] = [[] for _ in range(groups)]
    turn = 0
    for slots in by_worker.values():
        for slot in slots:
            members[turn % groups].extend(range(slot * agents_per_scene, (slot + 1) * agents_per_scene))
            turn += 1
    return [np.array(sorted(m), dtype=np.int64) for m in members if m]


class GroupStepper:
    """``send``/``recv`` of agent groups through an SB3 wrapper chain, with the wrappers' bookkeeping.

    ``VecNormalize`` (optional, outermost) normalises each group's observations and rewards and
    updates its statistics with the group's rows; ``VecMonitor`` needs nothing, because the env
    reports each finished episode's return and length itself.
    """

    def __init__(self, env: VecEnv) -> None:
        self.normalize: VecNormalize | None = None
        inner: Any = env
        if isinstance(inner, VecNormalize):
            self.normalize, inner = inner, inner.venv
        if isinstance(inner, VecMonitor):
            inner = inner.venv
        if not isinstance(inner, DroneEnvBase):
            raise TypeError(f"{type(inner).__name__} under the wrappers is not a visfly-dist env")
        self.env: DroneEnvBase = inner

    def send(self, actions: np.ndarray, ids: np.ndarray) -> None:
        self.env.send(actions, ids)

    def recv(self) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray, np.ndarray, list[dict[str, Any]]]:
        """The next group in: ``(ids, observation, rewards, dones, infos)``, normalised like the chain's ``step``."""
        result, ids_t = self.env.recv()
        obs, rewards, dones, infos = self.env.to_sb3(result)
        ids = ids_t.cpu().numpy()
        vn = self.normalize
        if vn is not None:
            if vn.training and vn.norm_obs:
                for key in vn.obs_rms:
                    vn.obs_rms[key].update(obs[key])
            obs = vn.normalize_obs(obs)
            if vn.training:
                vn.returns[ids] = vn.returns[ids] * vn.gamma + rewards
                vn.ret_rms.update(vn.returns[ids])
            rewards = vn.normalize_reward(rewards)
            for i in np.flatnonzero(dones):
                if "terminal_observation" in infos[i]:
                    infos[i]["terminal_observation"] = vn.normalize_obs(infos[i]["terminal_observation"])
            vn.returns[ids[dones]] = 0
        return ids, obs, rewards, dones, infos


class PipelinedPPO(UpdateThreadsPPO):
    """SB3 PPO (with :class:`UpdateThreadsPPO`'s update threads) whose rollout keeps one group of
    agents on the wire while the learner handles the other (see the module docstring).

    Attributes:
        groups: agent index arrays of the last rollout (empty before the first, or when falling back).
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.groups: list[np.ndarray] = []
        self._fallback_reason: str | None = None

    def _excluded_save_params(self) -> list[str]:
        return super()._excluded_save_params() + ["groups", "_fallback_reason"]

    def collect_rollouts(self, env: VecEnv, callback: BaseCallback, rollout_buffer: RolloutBuffer,
                         n_rollout_steps: int) -> bool:
        stepper, groups = self._plan(env)
        if stepper is None:
            return super().collect_rollouts(env, callback, rollout_buffer, n_rollout_steps)
        t0 = time.perf_counter()
        ok = self._collect_pipelined(stepper, groups, callback, rollout_buffer, n_rollout_steps)
        self.phase_seconds["rollout_s"] += time.perf_counter() - t0
        return ok

    def _plan(self, env: VecEnv) -> tuple[GroupStepper | None, list[np.ndarray]]:
        reason = None
        try:
            stepper = GroupStepper(env)
        except TypeError as exc:
            stepper, reason = None, str(exc)
        if stepper is not None:
            self.groups = agent_groups(stepper.env.aggregator.assignment(), stepper.env.agents_per_scene)
            if len(self.groups) < 2:
                stepper, reason = None, "one scene cannot be split into two groups"
        if self.use_sde:
            stepper, reason = None, "gSDE noise is drawn for all agents at once"
        if stepper is None:
            self.groups = []
            if reason != self._fallback_reason:
                print(f"pipelined rollout off: {reason}; using SB3's rollout loop", flush=True)
                self._fallback_reason = reason
        return stepper, self.groups

    def _act(self, obs: dict[str, np.ndarray]) -> tuple[np.ndarray, torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            actions, values, log_probs = self.policy(obs_as_tensor(obs, self.device))
        return actions.cpu().numpy(), values, log_probs

    def _collect_pipelined(self, stepper: GroupStepper, groups: list[np.ndarray], callback: BaseCallback,
                           rollout_buffer: RolloutBuffer, n_rollout_steps: int) -> bool:
        """SB3's ``collect_rollouts``, with each step's columns filled group by group."""
        assert self._last_obs is not None, "No previous observation was provided"
        self.policy.set_training_mode(False)
        rollout_buffer.reset()
        callback.on_rollout_start()
        n = self.n_envs
        low, high = self.action_space.low, self.action_space.high
        obs = {k: np.array(v) for k, v in self._last_obs.items()}  # type: ignore[union-attr]
        starts = np.array(self._last_episode_starts)
        # per step being filled: the columns SB3's loop would have, group by group
        pending: dict[int, dict[str, Any]] = {}
        done_count = np.zeros(len(groups), dtype=np.int64)  # steps taken in, per group
        index_of = {int(g[0]): i for i, g in enumerate(groups)}

        def record(step: int) -> dict[str, Any]:
            if step not in pending:
                pending[step] = {"obs": {k: np.empty_like(v) for k, v in obs.items()},
                                 "actions": np.empty((n, *self.action_space.shape), dtype=np.float32),
                                 "values": torch.empty(n, 1), "log_probs": torch.empty(n),
                                 "starts": np.empty(n, dtype=bool), "rewards": np.empty(n, dtype=np.float32),
                                 "dones": np.empty(n, dtype=bool), "infos": [None] * n, "in": 0}
            return pending[step]

        def act_and_send(gi: int, step: int) -> None:
            ids = groups[gi]
            group_obs = {k: v[ids] for k, v in obs.items()}
            actions, values, log_probs = self._act(group_obs)
            row = record(step)
            for k in obs:
                row["obs"][k][ids] = group_obs[k]
            row["actions"][ids] = actions
            row["values"][ids] = values.reshape(-1, 1)
            row["log_probs"][ids] = log_probs.reshape(-1)
            row["starts"][ids] = starts[ids]
            stepper.send(np.clip(actions, low, high), ids)

        for gi in range(len(groups)):
            act_and_send(gi, 0)
        for step in range(n_rollout_steps):
            while pending[step]["in"] < len(groups):
                ids, new_obs, rewards, dones, infos = stepper.recv()
                gi = index_of[int(ids[0])]
                row = record(int(done_count[gi]))
                done_count[gi] += 1
                for k in obs:
                    obs[k][ids] = new_obs[k]
                starts[ids] = dones
                row["rewards"][ids] = rewards
                row["dones"][ids] = dones
                for i, info in zip(ids, infos):
                    row["infos"][i] = info
                row["in"] += 1
                if done_count[gi] < n_rollout_steps:
                    act_and_send(gi, int(done_count[gi]))
            row = pending.pop(step)
            rewards, dones, infos = row["rewards"], row["dones"], row["infos"]
            self.num_timesteps += n
            callback.update_locals({"infos": infos, "dones": dones, "rewards": rewards, "new_obs": obs})
            if not callback.on_step():
                self._drain(stepper)
                return False
            self._update_info_buffer(infos, dones)
            for i in np.flatnonzero(dones):  # bootstrap truncated episodes, as SB3 does
                if infos[i].get("terminal_observation") is not None and infos[i].get("TimeLimit.truncated", False):
                    terminal = self.policy.obs_to_tensor(infos[i]["terminal_observation"])[0]
                    with torch.no_grad():
                        rewards[i] += self.gamma * self.policy.predict_values(terminal)[0].item()
            rollout_buffer.add(row["obs"], row["actions"], rewards, row["starts"], row["values"], row["log_probs"])
        self._last_obs, self._last_episode_starts = obs, starts
        with torch.no_grad():
            last_values = self.policy.predict_values(obs_as_tensor(obs, self.device))
        rollout_buffer.compute_returns_and_advantage(last_values=last_values, dones=starts)
        callback.update_locals({"infos": infos, "dones": dones, "rewards": rewards, "new_obs": obs})
        callback.on_rollout_end()
        return True

    @staticmethod
    def _drain(stepper: GroupStepper) -> None:
        """Take in what is still on the wire (a callback stopped the rollout early)."""
        while stepper.env.groups_in_flight:
            stepper.recv()
