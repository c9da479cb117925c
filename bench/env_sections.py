"""Where the env core's CPU goes in one step, on its own (no trainer, no policy).

    python bench/env_sections.py [--task navigation] [--num-envs 256] [--groups 1|2] [--steps 400] [--json out.json]

Steps the task's env with random actions, one plain ``step_tensor(terminal="ended")`` a step
(``--groups 1``, the 2-core trainer's path) or two halves of the agents sent and received in turn
(``--groups 2``: ``send``/``recv(terminal="ended")``, the overlapped trainer's path), and times the
sections listed below on the calling thread (``thread_time``: CPU, not waiting on the workers).
Figures are ms per step (one step of every agent, or of one group), after 30 warm-up steps;
sections nest (a parent includes its children), each wrapper adds about a microsecond.

The same code measured on its own, in a loop that calls one piece over and over ("hot"), costs 2-5x
less than inside the step, where each piece runs once between others: compare a section here with
a hot loop before concluding that a piece is slow in itself.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import torch
from learner_sections import Sections  # this folder: the same wrapper, thread CPU and wall per section

from visfly_dist import make_env
from visfly_dist.aggregator import aggregator, pool
from visfly_dist.client import core
from visfly_dist.dynamics import quadrotor

SECTIONS: list[tuple[Any, str, str]] = [
    (core.TensorEnv, "_send", "send"),
    (quadrotor.Quadrotor, "step", "send.physics"),
    (aggregator.Aggregator, "submit", "send.submit"),
    (pool.WorkerPool, "send", "send.submit.encode_and_write"),
    (core.TensorEnv, "precompute", "send.precompute"),
    (core.TensorEnv, "_finish", "finish"),
    (aggregator.Aggregator, "collect", "finish.collect"),
    (pool.WorkerPool, "gather", "finish.collect.wait_and_decode"),
    (core.TensorEnv, "_frame", "finish.frame"),
    (core.TensorEnv, "_merge", "finish.merge"),
    (core.TensorEnv, "get_success", "finish.success"),
    (core.TensorEnv, "get_failure", "finish.failure"),
    (core.TensorEnv, "get_reward", "finish.reward"),
    (core.TensorEnv, "_observation", "finish.observation"),
    (core.TensorEnv, "_take_swapped", "finish.swapped"),
    (core.TensorEnv, "_reset_agents", "finish.reset"),
    (core.TensorEnv, "_draw_next_starts", "finish.reset.draw_next_starts"),
    (quadrotor.Quadrotor, "restart", "finish.reset.restart"),
    (core.TensorEnv, "reset_agents_hook", "finish.reset.task_hook"),
    (aggregator.Aggregator, "note_resets", "finish.reset.note"),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", default="navigation")
    parser.add_argument("--num-envs", type=int, default=256)
    parser.add_argument("--groups", type=int, choices=(1, 2), default=1)
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(1)
    env = make_env(args.task, num_envs=args.num_envs, seed=0)
    timer = Sections()
    for owner, name, label in SECTIONS:
        # a hook the task overrides is wrapped on the task's class, where the env looks it up
        timer.wrap(type(env) if owner is core.TensorEnv and name in vars(type(env)) else owner, name, label)
    generator = torch.Generator().manual_seed(0)
    n = args.num_envs

    def actions(k: int) -> torch.Tensor:
        return torch.rand(k, 4, generator=generator) * 2 - 1

    def run(steps: int) -> None:
        if args.groups == 1:
            for _ in range(steps):
                env.step_tensor(actions(n), terminal="ended")
            return
        halves = [torch.arange(0, n // 2), torch.arange(n // 2, n)]
        for ids in halves:
            env.send(actions(len(ids)), ids)
        for _ in range(steps):
            _, ids = env.recv(terminal="ended")
            env.send(actions(len(ids)), ids)
        for _ in halves:
            env.recv(terminal="ended")

    try:
        env.reset()
        with torch.no_grad():
            run(30)
            timer.on = True
            start = time.thread_time()
            run(args.steps)
            total = time.thread_time() - start
            timer.on = False
    finally:
        env.close()
    what = "step of every agent" if args.groups == 1 else f"group step ({n // 2} agents)"
    print(f"{args.task}, {n} agents, {args.groups} group(s): {total * 1000 / args.steps:.3f} ms thread CPU per {what}")
    rows = {label: {"cpu_ms": timer.cpu[label] * 1000 / args.steps, "calls": timer.calls[label] / args.steps}
            for _, _, label in SECTIONS}
    for label, row in rows.items():
        print(f"  {label:34s} {row['cpu_ms']:7.3f} ms  calls {row['calls']:.2f}")
    if args.json:
        args.json.write_text(json.dumps({"task": args.task, "num_envs": n, "groups": args.groups, "steps": args.steps,
                                         "ms_per_step": total * 1000 / args.steps, "sections": rows}, indent=1))


if __name__ == "__main__":
    main()
