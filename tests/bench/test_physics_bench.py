"""``visfly-dist bench physics`` runs on a tiny size and writes well-formed JSON."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch

from visfly_dist.bench.physics import bench_physics

ROW_KEYS = {"agents", "mode", "grad", "agent_steps_per_s", "sim_seconds_per_s", "device"}


def test_bench_cli_writes_json_rows(tmp_path):
    out = tmp_path / "physics.json"
    proc = subprocess.run([sys.executable, "-m", "visfly_dist.cli", "bench", "physics", "--agents", "8", "--steps", "3",
                           "--no-compile", "--json", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "agent-steps/s" in proc.stdout
    rows = json.loads(out.read_text())["rows"]
    assert [(r["agents"], r["mode"], r["grad"]) for r in rows] == [(8, "eager", False), (8, "eager", True)]
    for row in rows:
        assert ROW_KEYS <= set(row) and row["device"] == "cpu"
        assert row["agent_steps_per_s"] > 0 and row["sim_seconds_per_s"] > 0
        assert row["agent_steps_per_s"] == pytest.approx(row["sim_seconds_per_s"] / row["ctrl_dt"])


def test_bench_function_for_the_suite():
    threads = torch.get_num_threads()
    rows = bench_physics([4, 6], modes=["eager"], grads=[False], device="cpu", steps=2)
    assert [r["agents"] for r in rows] == [4, 6] and all(r["threads"] == 1 for r in rows)
    assert torch.get_num_threads() == threads
    json.dumps(rows)
