"""``visfly-dist bench physics``: rows for every requested size, and the steps it times are the real dynamics."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch

import visfly_dist.bench.physics as physics_bench
from visfly_dist.bench.physics import BPTT_HORIZON, CTRL_DT, SIM_DT, bench_physics
from visfly_dist.dynamics import DynamicsConfig, Quadrotor

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


class _RecordingQuadrotor(Quadrotor):
    """The bench's own Quadrotor, unchanged, that also keeps what each ``step`` was given and returned."""

    made: list["_RecordingQuadrotor"] = []

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.calls = []
        _RecordingQuadrotor.made.append(self)

    def step(self, state, action):
        out = super().step(state, action)
        self.calls.append((state, action, out))
        return out


def test_bench_times_the_real_dynamics_for_every_requested_row(monkeypatch):
    """One row per (grad, agents) in order; each row's timed steps are ``steps`` control steps of the
    configuration it reports, hovering in place exactly as the plain dynamics does, and with grad the
    actions receive gradients (the backward passes are really part of the time)."""
    _RecordingQuadrotor.made = []
    monkeypatch.setattr(physics_bench, "Quadrotor", _RecordingQuadrotor)
    threads = torch.get_num_threads()
    steps = 2 * BPTT_HORIZON + 3
    rows = bench_physics([4, 6], modes=["eager"], grads=[False, True], device="cpu", steps=steps)
    assert torch.get_num_threads() == threads
    assert [(r["agents"], r["grad"]) for r in rows] == [(4, False), (6, False), (4, True), (6, True)]
    assert len(_RecordingQuadrotor.made) == len(rows)
    plain = Quadrotor(DynamicsConfig(controller="ctbr", ctrl_dt=CTRL_DT, sim_dt=SIM_DT, integrator="rk4",
                                     motor_lag=True), "visfly", num_agents=4)
    for row, quad in zip(rows, _RecordingQuadrotor.made):
        n = row["agents"]
        assert quad.num_agents == n and (quad.config.ctrl_dt, quad.config.sim_dt) == (row["ctrl_dt"], row["sim_dt"])
        assert (quad.config.controller, quad.config.integrator) == (row["controller"], row["integrator"])
        assert row["steps"] == steps and row["seconds"] > 0 and row["threads"] == 1
        assert row["agent_steps_per_s"] == pytest.approx(n * steps / row["seconds"])
        assert row["sim_seconds_per_s"] == pytest.approx(n * steps * CTRL_DT / row["seconds"])
        warmup = min(steps, 2 * BPTT_HORIZON if row["grad"] else 3)
        assert len(quad.calls) == warmup + steps
        # the timed rollout starts at (1, 1, 1) and holds it, step for step as the plain dynamics
        timed = quad.calls[warmup:]
        start = timed[0][0]
        assert torch.allclose(start.pos, torch.ones(n, 3))
        expected = plain.initial_state(pos=torch.ones(4, 3))
        hover = plain.hover_action().expand(4, 4)
        with torch.no_grad():
            for _ in range(BPTT_HORIZON):
                expected = plain.step(expected, hover)
        got = timed[BPTT_HORIZON - 1][2]
        assert torch.allclose(got.pos.detach()[:4], expected.pos, atol=1e-6)
        assert float((timed[-1][2].pos.detach() - 1.0).abs().max()) < 1e-3  # hover holds over the whole run
        action = timed[0][1]
        assert action.requires_grad == row["grad"]
        if row["grad"]:
            assert action.grad is not None and bool(torch.isfinite(action.grad).all())
            assert float(action.grad.abs().sum()) > 0
            # truncated BPTT: the state is detached every BPTT_HORIZON steps, not in between
            fresh = [i for i, (state, _, _) in enumerate(timed) if state.pos.grad_fn is None]
            assert fresh == list(range(0, steps, BPTT_HORIZON))
