"""``visfly-dist bench render`` runs tiny end to end (in-process and through a real worker) and writes its JSON."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from visfly_dist.bench.render import bench_poses
from visfly_dist.scene_worker.queries import ObstacleQueries
from visfly_dist.scene_worker.render_base import available_backends
from visfly_dist.scenes import generate_scene

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.worker
def test_bench_render_cli_writes_rows_for_every_backend_kind_and_place(tmp_path):
    out = tmp_path / "render.json"
    backends = list(available_backends())
    cmd = [sys.executable, "-m", "visfly_dist.cli", "bench", "render", "--backend", *backends, "--res", "16",
           "--agents", "4", "--kinds", "depth", "segmentation", "--quick", "--json", str(out)]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "frames_per_s" in done.stdout
    rows = json.loads(out.read_text())["rows"]
    frames = {(r["backend"], r["kind"], r["where"]) for r in rows if "frames_per_s" in r}
    assert frames == {(b, k, w) for b in backends for k in ("depth", "segmentation") for w in ("in_process", "worker")}
    for r in rows:
        if "frames_per_s" in r:
            assert r["res"] == 16 and r["agents"] == 4 and r["frames_per_s"] > 0
    (queries,) = [r for r in rows if r["kind"] == "queries"]
    assert queries["queries_per_s"] > 0 and 0 < queries["query_share_of_raycast_step"] < 1


def test_bench_poses_are_clear_of_obstacles_and_inside_bounds():
    scene = generate_scene("garage-stones", seed=0)
    poses = bench_poses(scene, 50, seed=1)
    assert poses.shape == (50, 7)
    assert (poses[:, :3] >= scene.bounds[0]).all() and (poses[:, :3] <= scene.bounds[1]).all()
    assert (ObstacleQueries(scene).distance(poses[:, :3]) > 0.3).all()
