"""``visfly-dist bench all`` on a tiny preset: every section runs, and JSON, plots and Markdown come out right."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest

from visfly_dist.bench import report
from visfly_dist.bench.suite import GOALS, PRESETS, SECTIONS, compute_ratios, run_section, run_suite
from visfly_dist.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """One real tiny run of the whole suite through the CLI (as a user would start it)."""
    out = tmp_path_factory.mktemp("bench")
    cmd = [sys.executable, "-m", "visfly_dist.cli", "bench", "all", "--tiny", "--json", str(out / "r.json"),
           "--plots", str(out / "plots"), "--md", str(out / "BENCHMARKS.md")]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=240)
    return out, proc


def test_tiny_suite_runs_every_section(tiny_run):
    out, proc = tiny_run
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    result = json.loads((out / "r.json").read_text())
    assert list(result["sections"]) == list(SECTIONS)
    for name, section in result["sections"].items():
        assert section["status"] == "ok", f"{name}: {section.get('error')}"
        assert section["elapsed_s"] >= 0
    # Progress lines name each section as it starts.
    for name in SECTIONS:
        assert f"[bench all] {name} ..." in proc.stdout


def test_tiny_suite_json_has_machine_figures_and_ratios(tiny_run):
    out, _ = tiny_run
    result = json.loads((out / "r.json").read_text())
    machine = result["machine"]
    for key in ("cpu_model", "cores", "python", "torch", "date", "git_commit", "command"):
        assert key in machine
    assert "bench all --tiny" in machine["command"]
    assert result["preset"] == "tiny" and result["total_s"] > 0
    sec = result["sections"]
    assert all(r["agent_steps_per_s"] > 0 for r in sec["physics"]["rows"])
    assert any(r.get("frames_per_s", 0) > 0 for r in sec["render"]["rows"])
    assert all(r["env_steps_per_s"] > 0 for r in sec["end_to_end"]["rows"] + sec["scaling"]["rows"])
    assert sorted({r["scenes"] for r in sec["scaling"]["rows"]}) == list(PRESETS["tiny"].scaling_scenes)
    stages = sec["end_to_end"]["rows"][0]["stages"]
    assert set(stages) == {"physics", "transport", "render", "queries", "other"}
    assert sum(stages.values()) == pytest.approx(1.0, abs=1e-3)
    assert sec["peer"]["physics"][0]["sim_seconds_per_s"] > 0 and sec["peer"]["depth"][0]["frames_per_s"] > 0
    depth = result["ratios"]["depth 64x64 frames/s"]
    assert depth["goal"] == GOALS["depth"]  # tiny runs 16x16 only, so there is no 64x64 ratio to compute
    assert depth["ratio"] is None


def test_tiny_suite_writes_plots_and_markdown(tiny_run):
    out, _ = tiny_run
    plots = sorted((out / "plots").glob("*.png"))
    assert {p.name for p in plots} == set(report.PLOT_FILES.values())
    for p in plots:
        assert p.read_bytes()[:8] == PNG_MAGIC and p.stat().st_size > 2000
    md = (out / "BENCHMARKS.md").read_text()
    assert md.startswith("# Benchmarks") and "## Goals" in md and "bench all --tiny" in md
    for name in report.PLOT_FILES.values():
        assert f"](plots/{name})" in md


def test_failing_section_is_recorded_and_the_run_goes_on():
    sizes = dataclasses.replace(PRESETS["tiny"], peer_seconds=0.0)  # peer_physics rejects no simulated time
    lines = []
    section = run_section("peer", sizes, lines.append)
    assert section["status"] == "error" and "ConfigError" in section["error"] and "seconds=0.0" in section["error"]
    assert any("FAILED" in line for line in lines)
    result = {"sections": {"peer": section}}
    assert compute_ratios(result)["depth 64x64 frames/s"]["ratio"] is None
    assert "ERROR" in report.text_report(result)


def test_ratios_use_the_fastest_of_ours_against_the_peer():
    result = {"sections": {
        "physics": {"status": "ok", "rows": [
            {"agents": 100, "mode": "eager", "grad": False, "sim_seconds_per_s": 500.0},
            {"agents": 100, "mode": "compiled", "grad": False, "sim_seconds_per_s": 4000.0},
            {"agents": 1000, "mode": "compiled", "grad": False, "sim_seconds_per_s": 9e9}]},
        "render": {"status": "ok", "rows": [
            {"backend": "raycast", "kind": "depth", "res": 64, "frames_per_s": 1500.0},
            {"backend": "egl", "kind": "depth", "res": 64, "frames_per_s": 120.0},
            {"backend": "raycast", "kind": "depth", "res": 256, "frames_per_s": 9e9}]},
        "peer": {"status": "ok", "physics": [{"drones": 100, "sim_seconds_per_s": 400.0},
                                             {"drones": 1000, "sim_seconds_per_s": 40.0}],
                 "depth": [{"res": 64, "frames_per_s": 60.0}]},
    }}
    ratios = compute_ratios(result)
    at_100 = ratios["physics sim-s/s, 100 drones"]
    assert at_100["ratio"] == pytest.approx(10.0) and at_100["met"] and "compiled" in at_100["note"]
    # The goal is set at the first peer size only; the larger one is shown for scaling.
    at_1000 = ratios["physics sim-s/s, 1,000 drones"]
    assert at_1000["ratio"] == pytest.approx(9e9 / 40.0) and at_1000["goal"] is None and at_1000["met"] is None
    assert ratios["depth 64x64 frames/s"]["ratio"] == pytest.approx(25.0)
    assert "raycast" in ratios["depth 64x64 frames/s"]["note"]


def test_unknown_section_is_a_config_error():
    with pytest.raises(ConfigError, match="unknown sections.*'rendering'"):
        run_suite(PRESETS["tiny"], ("rendering",))


def test_rewriting_the_report_keeps_the_hand_written_part(tiny_run, tmp_path):
    """``--md`` on an existing BENCHMARKS.md replaces the generated part and keeps what follows the mark."""
    out, _ = tiny_run
    result = json.loads((out / "r.json").read_text())
    md = tmp_path / "BENCHMARKS.md"
    hand = f"{report.HAND_WRITTEN_MARK}\n\n## A study\n\nbefore 1, after 2\n"
    md.write_text("# Benchmarks\n\nstale generated figures\n\n" + hand)
    report.write_markdown(result, md, out / "plots")
    text = md.read_text()
    assert "stale generated figures" not in text and "## Goals" in text
    assert text.endswith(hand) and text.count(report.HAND_WRITTEN_MARK) == 1
    report.write_markdown(result, md, out / "plots")  # idempotent
    assert md.read_text() == text
