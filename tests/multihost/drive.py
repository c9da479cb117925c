"""A trainer stand-in for the multi-host tests: ``make_env`` with remote workers only, random actions.

Run as ``python tests/multihost/drive.py --connect EP --run-id R [--zenoh-config FILE]``. Prints one
JSON line every ``--report-every`` steps (``steps``, ``workers``, ``assignment``: slot -> worker)
and keeps stepping until a line ``stop`` (or EOF) arrives on stdin, then closes the env and prints
``{"done": steps}``. Every step must succeed: an exception ends the process with its message.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--connect", required=True)
    parser.add_argument("--run-id", required=True)
    parser.add_argument("--zenoh-config", default=None)
    parser.add_argument("--report-every", type=int, default=20)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(asctime)s trainer %(levelname)s %(message)s")

    import torch

    from visfly_dist import make_env
    from visfly_dist.aggregator import PoolConfig
    from visfly_dist.protocol import CameraSpec

    torch.set_num_threads(1)
    pool = PoolConfig(connect=(args.connect,), num_local_workers=0, run_id=args.run_id, min_workers=2,
                      step_timeout_s=3.0, startup_timeout_s=30.0, zenoh_config=args.zenoh_config)
    env = make_env("navigation", num_envs=4, agents_per_scene=2, scenes=("gen:pillars",), pool=pool,
                   cameras=(CameraSpec(name="depth", kind="depth", width=16, height=12),), seed=0)
    stop = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.readline(), stop.set()), daemon=True).start()
    rng = np.random.default_rng(0)
    steps = 0
    try:
        env.reset()
        while not stop.is_set():
            env.step(rng.uniform(-1, 1, (env.num_envs, 4)).astype(np.float32))
            steps += 1
            if steps % args.report_every == 0:
                agg = env.aggregator
                held = {h["worker_id"]: sorted(h.get("scenes", [])) for h in agg.health()} \
                    if steps % (5 * args.report_every) == 0 else None
                print(json.dumps({"steps": steps, "workers": agg.workers, "held": held,
                                  "served": [[s.worker, s.key] for s in agg.table.slots if s.worker],
                                  "assignment": {str(k): v for k, v in agg.assignment().items()}}), flush=True)
    finally:
        env.close()
    print(json.dumps({"done": steps}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
