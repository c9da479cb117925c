"""Learner CPU per 1,000 rollout env steps outside the policy network, for any checkout.

    cd OTHER_CHECKOUT && PYTHONPATH=$PWD python /path/to/bench/learner_cpu_any_tree.py [--num-envs 256] [--timesteps 16384]

``visfly-dist bench train`` reports this figure (``learner_cpu_s_per_1k``) since it was added; this
script measures it the same way for a checkout older than that (the round's starting point), so that
both are measured in one session, interleaved: the training process's CPU time (every thread) while
rollouts are collected, minus the policy's forward passes. It trains the task's default trainer
with ``--num-envs`` envs and prints one JSON line: the figure with the policy timed on its own
thread (as ``bench train`` does) and with the policy timed as the whole process's CPU while it runs
(fair to a forward pass that uses several threads), the policy's own share, and rollout env-steps/s.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import tempfile
import time
from typing import Any, Callable

from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.policies import ActorCriticPolicy

import visfly_dist
from visfly_dist.training.config import TrainConfig
from visfly_dist.training.ppo import train

totals = {"collect_cpu": 0.0, "collect_wall": 0.0, "policy_thread": 0.0, "policy_process": 0.0}


def timed_collection(method: Callable[..., Any]) -> Callable[..., Any]:
    def timed(self: Any, *args: Any, **kwargs: Any) -> Any:
        cpu, wall = time.process_time(), time.perf_counter()
        try:
            return method(self, *args, **kwargs)
        finally:
            totals["collect_cpu"] += time.process_time() - cpu
            totals["collect_wall"] += time.perf_counter() - wall
    return timed


def timed_policy(method: Callable[..., Any]) -> Callable[..., Any]:
    def timed(self: Any, *args: Any, **kwargs: Any) -> Any:
        thread, process = time.thread_time(), time.process_time()
        try:
            return method(self, *args, **kwargs)
        finally:
            totals["policy_thread"] += time.thread_time() - thread
            totals["policy_process"] += time.process_time() - process
    return timed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", default="navigation")
    parser.add_argument("--num-envs", type=int, default=256)
    parser.add_argument("--timesteps", type=int, default=16384)
    args = parser.parse_args()
    OnPolicyAlgorithm.collect_rollouts = timed_collection(OnPolicyAlgorithm.collect_rollouts)
    try:  # the tensor trainer, where the checkout has one
        from visfly_dist.training.tensor_ppo import TensorPPO
        TensorPPO.collect = timed_collection(TensorPPO.collect)
    except ImportError:
        pass
    ActorCriticPolicy.forward = timed_policy(ActorCriticPolicy.forward)
    ActorCriticPolicy.predict_values = timed_policy(ActorCriticPolicy.predict_values)
    cfg = TrainConfig(task=args.task, timesteps=args.timesteps, seed=0, out=tempfile.mkdtemp(prefix="learner-cpu-"),
                      checkpoint_every=0, progress=False, num_envs=args.num_envs)
    with contextlib.redirect_stdout(io.StringIO()):
        result = train(cfg)
    per_1k = 1000.0 / result.timesteps
    print(json.dumps({
        "checkout": visfly_dist.__file__, "task": args.task, "num_envs": args.num_envs, "timesteps": result.timesteps,
        "learner_cpu_s_per_1k": round((totals["collect_cpu"] - totals["policy_thread"]) * per_1k, 4),
        "learner_cpu_s_per_1k_policy_as_process": round((totals["collect_cpu"] - totals["policy_process"]) * per_1k, 4),
        "policy_cpu_s_per_1k": round(totals["policy_process"] * per_1k, 4),
        "rollout_env_steps_per_s": round(result.timesteps / totals["collect_wall"], 1)}))


if __name__ == "__main__":
    main()
