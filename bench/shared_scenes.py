"""Start-up and worker memory for one user mesh over 16 slots on one worker (shared scenes).

    python bench/shared_scenes.py LABEL

Makes a 655k-triangle PLY (a floor and eight fine spheres) under ``bench/results/tmp-shared-scenes/``,
then ``make_env("navigation", num_envs=16, scenes=["big.ply"])`` with one raycast worker, and prints
one JSON line: ``make_env`` seconds and the worker's resident memory after it.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import trimesh

import visfly_dist
from visfly_dist.aggregator.config import PoolConfig


def big_mesh(path: Path) -> None:
    """A floor with a ceiling triangle (the flight box) and eight spheres of 81,920 triangles each."""
    floor = trimesh.Trimesh([[-2, -5, 0], [12, -5, 0], [12, 5, 0], [-2, 5, 0], [0, 0, 4], [1, 0, 4], [0, 1, 4]],
                            [[0, 1, 2], [0, 2, 3], [4, 5, 6]])
    balls = [trimesh.creation.icosphere(subdivisions=6, radius=0.4).apply_translation((4 + 2 * (i % 4), -3 + 2 * (i // 4), 1.5))
             for i in range(8)]
    trimesh.util.concatenate([floor, *balls]).export(path)


def worker_rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as status:
        line = next(row for row in status if row.startswith("VmRSS"))
    return int(line.split()[1]) / 1024


def main() -> None:
    root = Path(__file__).resolve().parent / "results" / "tmp-shared-scenes"
    root.mkdir(parents=True, exist_ok=True)
    path = root / "big.ply"
    if not path.exists():
        big_mesh(path)
    started = time.perf_counter()
    env = visfly_dist.make_env("navigation", num_envs=16, scenes=["big.ply"],
                               pool=PoolConfig(num_local_workers=1, backend="raycast", scene_roots=(str(root),)))
    made = time.perf_counter() - started
    rss = worker_rss_mb(next(iter(env.aggregator.local_worker_pids().values())))
    env.reset()
    env.step(np.zeros((16, 4), np.float32))
    env.close()
    print(json.dumps({"tree": sys.argv[1] if len(sys.argv) > 1 else "now", "make_env_s": round(made, 2),
                      "worker_rss_mb": round(rss), "triangles": len(trimesh.load(path).faces)}))


if __name__ == "__main__":
    main()
