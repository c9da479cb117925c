"""``visfly-dist bench step`` on a tiny batch: real workers, real Zenoh, well-formed rows."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from visfly_dist.bench.step import (NO_RESETS, ROWS, STAGES, RowSpec, bench_rows, bench_step, expand_rows,
                                    measure_interleaved, measure_steps)
from visfly_dist.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]


def test_bench_step_tiny_row_times_each_stage_once():
    """The env's own stage timings of a tiny navigation batch: every stage the step goes through took
    time, the measured stages are disjoint parts of the step (together no longer than it; ``other`` is
    the rest, clamped at 0, so an overlap or a double count shows here), and the rates agree."""
    rows = bench_step(agents=4, workers=[1], res=16, steps=2, warmup=1)
    assert len(rows) == 1
    row = rows[0]
    assert row["agents"] == 4 and row["workers"] == 1 and row["scenes"] == 1 and row["res"] == 16
    assert row["steps"] == 2 and row["timings"] == "env"
    assert set(row["stages"]) == set(STAGES) and set(row["stage_ms"]) == set(STAGES)
    ms = row["stage_ms"]
    # Every step flies the dynamics, round-trips to the worker, renders depth and queries obstacles.
    assert all(ms[stage] > 0 for stage in ("physics", "transport", "render", "queries")), ms
    measured = sum(ms[stage] for stage in STAGES if stage != "other")
    assert measured <= row["step_ms"] + 0.002, (measured, row["step_ms"])  # 0.002: rounding of 4 stages
    assert ms["other"] == pytest.approx(row["step_ms"] - measured, abs=0.003)
    assert row["overhead_ms"] == pytest.approx(ms["transport"] + ms["other"], abs=2e-3)
    total = sum(ms.values())
    assert all(row["stages"][k] == pytest.approx(ms[k] / total, abs=2e-3) for k in STAGES), row["stages"]
    assert row["env_steps_per_s"] * row["step_ms"] / 1e3 == pytest.approx(row["agents"])


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


def test_expand_rows_groups_and_names_in_order_once():
    names = [r.name for r in expand_rows(["resets", "train16", "layout"])]
    assert names == ["resets", "no_resets", "train16", "train64", "one_scene"]
    assert [r.name for r in expand_rows(["all"])] == list(ROWS)
    with pytest.raises(ConfigError, match=r"unknown bench step row 'fast'; valid rows: .*groups"):
        expand_rows(["fast"])


def test_rows_reset_heavy_against_none_and_ratio():
    """Tiny versions of the reset pair: the reset row really resets every agent every 2 steps."""
    specs = [RowSpec("resets", 2, 2, max_episode_steps=2), RowSpec("no_resets", 2, 2, max_episode_steps=NO_RESETS)]
    out = bench_rows(specs, steps=4, warmup=1, workers=1, res=8)
    resets, none = out["rows"]
    assert resets["timings"] == none["timings"] == "env" and resets["steps"] == none["steps"] == 4
    assert resets["row"] == "resets" and none["row"] == "no_resets" and resets["scenes"] == 2
    assert resets["resets"] >= 4  # 2 agents x 4 steps, done every second step (crashes can only add)
    assert none["resets"] <= resets["resets"]
    assert resets["overhead_ms"] == pytest.approx(resets["stage_ms"]["transport"] + resets["stage_ms"]["other"],
                                                  abs=2e-3)
    (ratio,) = out["ratios"]
    assert ratio["ratio"].startswith("resets / no_resets") and ratio["value"] == pytest.approx(
        resets["step_ms"] / none["step_ms"], rel=1e-2)


def test_latency_row_runs_remote_workers_behind_the_proxy():
    out = bench_rows([RowSpec("delay20", 2, 2, delay_ms=20)], steps=3, warmup=1, workers=1, res=8)
    (row,) = out["rows"]
    assert row["delay_ms"] == 20 and row["shm"] is False and row["workers"] == 1
    # Every step waits at least one round trip through the proxy.
    assert row["step_ms"] >= 20 and row["stage_ms"]["render"] > 0


def test_env_step_timings_are_used_when_the_env_reports_them():
    class FakeEnv:
        """The measured surface of an env that times its own steps."""

        num_envs = 2

        def __init__(self):
            self.quad = type("Q", (), {"hover_action": staticmethod(lambda: torch.zeros(4))})()
            self.step_timings = {}

        def reset(self):
            return {}

        def step(self, actions):
            time.sleep(0.01)
            self.step_timings = {"physics_s": 0.001, "render_s": 0.004, "query_s": 0.001, "transport_s": 0.002,
                                 "total_s": 0.01}
            return {}, np.zeros(2), np.zeros(2, bool), [{}, {}]

    row = measure_steps(FakeEnv(), steps=3, warmup=1)
    assert row["timings"] == "env"
    assert row["stage_ms"]["render"] == pytest.approx(4.0) and row["stage_ms"]["transport"] == pytest.approx(2.0)
    assert row["stage_ms"]["other"] == pytest.approx(row["step_ms"] - 8.0, abs=0.01)


def test_interleaved_rows_take_turns_in_blocks():
    """Two envs measured together step in blocks, alternating which goes first; each row counts its own steps."""
    calls = []

    class FakeEnv:
        num_envs = 2

        def __init__(self, name):
            self.name, self.step_timings = name, {}
            self.quad = type("Q", (), {"hover_action": staticmethod(lambda: torch.zeros(4))})()

        def reset(self):
            return {}

        def step(self, actions):
            calls.append(self.name)
            self.step_timings = {"physics_s": 0.0, "render_s": 0.0, "query_s": 0.0, "transport_s": 0.0}
            return {}, np.zeros(2), np.ones(2, bool) if self.name == "a" else np.zeros(2, bool), [{}, {}]

    rows = measure_interleaved([FakeEnv("a"), FakeEnv("b")], steps=5, warmup=1, block=2)
    assert calls == ["a", "b"] + ["a", "a", "b", "b", "b", "b", "a", "a", "a", "b"]
    assert [r["steps"] for r in rows] == [5, 5] and [r["resets"] for r in rows] == [10, 0]
    assert all(r["timings"] == "env" for r in rows)


def test_bench_step_rows_cli_rejects_unknown_row():
    cmd = [sys.executable, "-m", "visfly_dist.cli", "bench", "step", "--rows", "nope"]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0 and "unknown bench step row 'nope'" in proc.stdout + proc.stderr
