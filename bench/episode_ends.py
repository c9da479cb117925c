"""How episodes end around a killed worker and under scene swaps: counts per end cause.

    python bench/episode_ends.py [--task navigation] [--steps 300] [--kill-at 60] [--hold 0 30]

For each ``lost_hold_s`` in ``--hold`` (0 cuts lost agents at once, as before holding existed; no
``--hold``: the env's default), one env with two local workers (the task's defaults otherwise:
scenes, swaps; ``--swap-every`` overrides the swap period) is stepped with a fixed noisy-hover
policy (hover thrust plus Gaussian noise of std ``--noise``: episodes of every length); at step
``--kill-at`` (-1: never) one worker is SIGKILLed (it is respawned, as by default). It prints one JSON line per setting: episodes per end cause (``lost`` and ``swapped`` among them),
agent-steps held, and the seconds from the kill until every agent was served again.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import time
from collections import Counter

import numpy as np

from visfly_dist.aggregator import PoolConfig
from visfly_dist.tasks import make_env
from visfly_dist.tasks.outcomes import end_cause


def run(task: str, steps: int, kill_at: int, hold: float | None, num_envs: int, seed: int,
        swap_every: int | None = None, noise: float = 0.3) -> dict:
    settings: dict = {} if hold is None else {"lost_hold_s": hold}
    if swap_every is not None:
        settings["swap_every_resets"] = swap_every
    env = make_env(task, num_envs=num_envs, seed=seed, pool=PoolConfig(num_local_workers=2, backend="raycast"),
                   **settings)
    causes: Counter[str] = Counter()
    cut_by_swap = 0  # episodes cut because their scene was swapped (the env's ``swapped`` flag; the
    # ``swapped`` cause also counts teammates cut by a teammate's end in team tasks)
    held_steps, killed_at, served_at = 0, None, None
    rng = np.random.default_rng(seed)
    started = time.monotonic()
    try:
        env.reset()
        hover = np.tile(env.quad.hover_action().numpy(), (env.num_envs, 1))
        for step in range(steps):
            if step == kill_at:
                victim = env.aggregator.workers[0]
                os.kill(env.aggregator.local_worker_pids()[victim], signal.SIGKILL)
                killed_at = time.monotonic()
            actions = np.clip(hover + rng.normal(0.0, noise, hover.shape), -1, 1).astype(np.float32)
            _, _, dones, infos = env.step(actions)
            held = sum(bool(i.get("held")) for i in infos)
            held_steps += held
            lost_now = held or any(i.get("lost") for i in infos)
            if killed_at is not None and served_at is None and step > kill_at and not lost_now:
                served_at = time.monotonic()
            for done, info in zip(dones, infos):
                if done:
                    cut_by_swap += bool(info.get("swapped"))
                    causes[end_cause(info, info["episode"]["l"], env.config.max_episode_steps)] += 1
    finally:
        env.close()
    return {"task": task, "lost_hold_s": hold, "swap_every_resets": env.config.swap_every_resets, "steps": steps, "num_envs": num_envs,
            "episodes": sum(causes.values()), "ends": dict(causes), "cut_by_scene_swap": cut_by_swap, "held_agent_steps": held_steps,
            "recovery_s": None if served_at is None else round(served_at - killed_at, 2),
            "killed_after_s": None if killed_at is None else round(killed_at - started, 2),
            "seconds": round(time.monotonic() - started, 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="navigation")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--kill-at", type=int, default=60)
    parser.add_argument("--hold", type=float, nargs="+", default=[None])
    parser.add_argument("--num-envs", type=int, default=32)
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--swap-every", type=int, default=None)
    parser.add_argument("--noise", type=float, default=0.3)
    args = parser.parse_args()
    for hold in args.hold:
        print(json.dumps(run(args.task, args.steps, args.kill_at, hold, args.num_envs, args.seed, args.swap_every,
                             args.noise)), flush=True)


if __name__ == "__main__":
    main()
