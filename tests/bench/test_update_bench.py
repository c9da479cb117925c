"""``visfly-dist bench update``: one real PPO update of a task's default policy, timed."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from visfly_dist.bench.update import bench_update


@pytest.mark.parametrize("mode", ["sharded", "openmp"])
def test_update_row_counts_the_task_defaults(mode):
    row = bench_update("hover", threads=2 if mode == "sharded" else 1, reps=1, mode=mode)
    assert row["mode"] == mode
    assert row["samples"] == 16 * 128 and row["epochs"] == 5 and row["batch_size"] == 512
    assert row["update_cpu_s"] > 0 and row["update_wall_s"] > 0
    # update_cpu_s is rounded to the millisecond: compare within that rounding, not a relative error
    cpu_rounding_ms = 0.0005 / (2048 * 5) * 1e3
    assert row["ms_per_sample_pass"] == pytest.approx(row["update_cpu_s"] / (2048 * 5) * 1e3,
                                                      abs=cpu_rounding_ms + 1e-6)


def test_bad_arguments_fail_with_one_line():
    done = subprocess.run([sys.executable, "-m", "visfly_dist.cli", "bench", "update", "--reps", "0"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode != 0 and "--reps 0" in done.stderr and "Traceback" not in done.stderr


def test_child_mode_prints_json_rows(tmp_path):
    done = subprocess.run([sys.executable, "-m", "visfly_dist.cli", "bench", "update", "--task", "hover", "--reps", "1",
                           "--modes", "openmp", "--child"], capture_output=True, text=True, timeout=300, check=True)
    rows = json.loads(done.stdout.strip().splitlines()[-1])
    assert [(r["task"], r["mode"], r["threads"]) for r in rows] == [("hover", "openmp", 1)]
