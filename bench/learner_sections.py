"""Where the learner's main thread spends a training step, section by section, in real training.

    python bench/learner_sections.py [--timesteps 196608] [--num-envs N] [--overlap] [--json out.json]

Trains the task's default trainer with the host plan (any option left out is the plan's, as with
``visfly-dist train``) and times, on the training thread only, the sections of the loop that the
list below names: wall time (``perf_counter``, which counts waiting on the workers and on the GPU)
and thread CPU time (``thread_time``). The first rollout (warm-up, CUDA graph captures) is left
out. Figures are per env step of the whole batch (one step of every agent), so a section's share
of the loop is its wall figure over ``loop`` (collect + update). Nested sections are included in
their parents; a section called from two parents is counted once, under its own name.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import io
import json
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable

from visfly_dist.aggregator import aggregator, pool
from visfly_dist.client import core
from visfly_dist.dynamics import quadrotor
from visfly_dist.training import device_stage, graphed_policy, tensor_ppo
from visfly_dist.training.config import TrainConfig
from visfly_dist.training.ppo import train

SECTIONS: list[tuple[Any, str, str]] = [
    (tensor_ppo.TensorPPO, "collect", "collect"),
    (tensor_ppo.TensorPPO, "update", "update"),
    (tensor_ppo.TensorPPO, "_act", "collect.act"),
    (graphed_policy.GraphedForward, "__call__", "collect.act.forward"),
    (tensor_ppo.Rollout, "store_observation", "collect.act.store"),
    (tensor_ppo.TensorPPO, "_take", "collect.take"),
    (device_stage.DeviceStage, "__call__", "collect.take.stage"),
    (tensor_ppo.Normalizer, "observe", "collect.take.norm_obs"),
    (tensor_ppo.Normalizer, "reward", "collect.take.norm_reward"),
    (tensor_ppo.TensorPPO, "_record_episodes", "collect.take.episodes"),
    (core.TensorEnv, "step_tensor", "collect.env_step"),
    (core.TensorEnv, "send", "collect.env_send"),
    (core.TensorEnv, "recv", "collect.env_recv"),
    (core.TensorEnv, "_send", "env.send"),
    (quadrotor.Quadrotor, "step", "env.send.physics"),
    (aggregator.Aggregator, "submit", "env.send.submit"),
    (core.TensorEnv, "_finish", "env.finish"),
    (aggregator.Aggregator, "collect", "env.finish.collect"),
    (pool.WorkerPool, "wait_any", "env.finish.collect.wait"),
    (core.TensorEnv, "_reset_agents", "env.finish.resets"),
    (tensor_ppo.Rollout, "compute_gae", "collect.gae"),
    (graphed_policy.GraphedForward, "verify", "update.verify_graphs"),
]


class Sections:
    """Wall and thread-CPU seconds per section, counted only while ``on`` and on the thread that made it."""

    def __init__(self) -> None:
        self.wall: collections.Counter[str] = collections.Counter()
        self.cpu: collections.Counter[str] = collections.Counter()
        self.calls: collections.Counter[str] = collections.Counter()
        self.on = False
        self.thread = threading.get_ident()

    def wrap(self, owner: Any, name: str, label: str) -> None:
        method: Callable[..., Any] = getattr(owner, name)

        def timed(*args: Any, **kwargs: Any) -> Any:
            if not self.on or threading.get_ident() != self.thread:  # the film thread steps an env too
                return method(*args, **kwargs)
            wall, cpu = time.perf_counter(), time.thread_time()
            try:
                return method(*args, **kwargs)
            finally:
                self.wall[label] += time.perf_counter() - wall
                self.cpu[label] += time.thread_time() - cpu
                self.calls[label] += 1

        setattr(owner, name, timed)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="navigation")
    parser.add_argument("--timesteps", type=int, default=196_608)
    parser.add_argument("--num-envs", type=int)
    parser.add_argument("--overlap", action=argparse.BooleanOptionalAction, help="default: the host plan's")
    parser.add_argument("--json", help="write the figures here too")
    args = parser.parse_args()
    sections = Sections()
    for owner, name, label in SECTIONS:
        sections.wrap(owner, name, label)
    rollouts, steps = [0], [0]
    collect = tensor_ppo.TensorPPO.collect

    def counted_collect(self: tensor_ppo.TensorPPO) -> None:
        sections.on = rollouts[0] >= 1  # the first rollout captures graphs and warms caches
        collect(self)
        if sections.on:
            steps[0] += self.n_steps
        rollouts[0] += 1

    tensor_ppo.TensorPPO.collect = counted_collect  # type: ignore[method-assign]
    out = Path(tempfile.mkdtemp(prefix="visfly-sections-"))
    cfg = TrainConfig(task=args.task, timesteps=args.timesteps, num_envs=args.num_envs, overlap=args.overlap, seed=0,
                      out=str(out), checkpoint_every=0, progress=False)
    wall = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        train(cfg)
    wall = time.perf_counter() - wall
    recorded = json.loads((out / "config.json").read_text())
    plan = {k: recorded.get(k) for k in ("device", "num_envs", "workers", "worker_threads", "overlap", "n_steps",
                                         "batch_size")}
    n = max(steps[0], 1)
    loop = sections.wall["collect"] + sections.wall["update"]
    rows = {label: {"wall_ms": 1e3 * sections.wall[label] / n, "cpu_ms": 1e3 * sections.cpu[label] / n,
                    "calls": sections.calls[label] / n} for _, _, label in SECTIONS}
    result = {"task": args.task, "timesteps": args.timesteps, "measured_steps": steps[0], "wall_s": wall,
              "plan": plan, "loop_ms_per_step": 1e3 * loop / n, "sections": rows}
    print("plan:", ", ".join(f"{k} {v}" for k, v in plan.items()))
    print(f"{steps[0]} batch steps measured; loop {1e3 * loop / n:.2f} ms per batch step")
    print(f"{'section':34s} {'wall ms':>8s} {'cpu ms':>8s} {'calls':>6s}")
    for label, row in rows.items():
        print(f"{label:34s} {row['wall_ms']:8.3f} {row['cpu_ms']:8.3f} {row['calls']:6.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
