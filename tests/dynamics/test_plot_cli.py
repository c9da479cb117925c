"""``visfly-dist plot step-response`` writes the PS and LV figures."""

from __future__ import annotations

from visfly_dist.cli import main


def test_step_response_plot_writes_two_pngs(tmp_path):
    assert main(["plot", "step-response", "--out", str(tmp_path), "--agents", "2", "--duration", "0.5"]) == 0
    for name in ("ps_step_response.png", "lv_step_response.png"):
        data = (tmp_path / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
