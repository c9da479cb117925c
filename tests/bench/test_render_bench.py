"""``visfly-dist bench render`` runs tiny end to end (in-process and through a real worker) and writes its JSON."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from visfly_dist.bench.render import available_tracers, bench_poses, goal_rows
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
    if "raycast" in backends:  # every tracer on 1 and 2 threads, side by side, with frames per CPU-second
        tracers = available_tracers()
        measured = {(r["tracer"], r["threads"], r["kind"]) for r in rows
                    if r["backend"] == "raycast" and r["where"] == "in_process"}
        assert measured == {(t, n, k) for t in tracers for n in (1, 2) for k in ("depth", "segmentation")}
        assert all(r["cpu_frames_per_s"] > 0 for r in rows if r["where"] == "in_process" and "frames_per_s" in r)


def test_goal_rows_are_ratios_of_the_runs_own_rows():
    def row(tracer, threads, res, fps, cpu):
        return {"backend": "raycast", "tracer": tracer, "threads": threads, "res": res, "kind": "depth",
                "where": "in_process", "frames_per_s": fps, "cpu_frames_per_s": cpu}

    rows = [row("native", 1, 64, 4000.0, 4000.0), row("embreex", 1, 64, 1000.0, 1500.0),
            row("native", 2, 64, 7600.0, 3900.0), row("native", 1, 256, 400.0, 400.0)]
    goals = {g["goal"]: g for g in goal_rows(rows)}
    assert goals["native / embreex per core, 64x64 depth"]["value"] == pytest.approx(4000 / 1500)
    assert goals["native / embreex per core, 64x64 depth"]["met"]
    assert goals["native 2 threads / 1 thread, 64x64 depth"]["value"] == pytest.approx(1.9)
    assert goals["native 2 threads, 64x64 depth frames/s"]["met"]
    assert "native / embreex per core, 256x256 depth" not in goals       # no embreex 256 row: left out


def test_bench_poses_are_clear_of_obstacles_and_inside_bounds():
    scene = generate_scene("garage-stones", seed=0)
    poses = bench_poses(scene, 50, seed=1)
    assert poses.shape == (50, 7)
    assert (poses[:, :3] >= scene.bounds[0]).all() and (poses[:, :3] <= scene.bounds[1]).all()
    assert (ObstacleQueries(scene).distance(poses[:, :3]) > 0.3).all()
