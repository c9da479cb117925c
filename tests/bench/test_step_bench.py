"""``visfly-dist bench step`` on a tiny batch: real workers, real Zenoh, well-formed rows."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from visfly_dist.bench.step import STAGES, bench_step
from visfly_dist.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]


def test_bench_step_tiny_rows_add_up():
    rows = bench_step(agents=4, workers=[1], res=16, steps=2, warmup=1)
    assert len(rows) == 1
    row = rows[0]
    assert row["agents"] == 4 and row["workers"] == 1 and row["scenes"] == 1 and row["res"] == 16
    assert row["env_steps_per_s"] > 0 and row["step_ms"] > 0
    assert set(row["stages"]) == set(STAGES) and set(row["stage_ms"]) == set(STAGES)
    assert sum(row["stages"].values()) == pytest.approx(1.0, abs=1e-3)
    # Every step renders and steps the dynamics, so neither stage can be empty.
    assert row["stage_ms"]["render"] > 0 and row["stage_ms"]["physics"] > 0
    assert sum(row["stage_ms"].values()) == pytest.approx(row["step_ms"], rel=0.05)


def test_bench_step_rejects_more_scenes_than_agents():
    with pytest.raises(ConfigError, match="agents=2 must be at least scenes=4"):
        bench_step(agents=2, workers=[1], scenes=4, steps=1)


def test_bench_step_cli_writes_json(tmp_path):
    out = tmp_path / "step.json"
    cmd = [sys.executable, "-m", "visfly_dist.cli", "bench", "step", "--agents", "4", "--workers", "1", "--res", "16",
           "--no-shm", "--steps", "2", "--warmup", "0", "--json", str(out)]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    data = json.loads(out.read_text())
    assert data["rows"][0]["shm"] is False and data["rows"][0]["env_steps_per_s"] > 0
    assert "env_steps_per_s" in proc.stdout
