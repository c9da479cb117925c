"""Fixtures of the multi-host tests: the shipped Zenoh configs with fresh certificates."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


@pytest.fixture
def deploy_configs(tmp_path: Path):
    """``deploy_configs(router_host)``: a copy of ``deploy/zenoh`` with certificates for
    ``router_host`` made by ``deploy/gen-certs.sh`` and ``users.txt`` from the example."""

    def make(router_host: str) -> Path:
        out = tmp_path / f"zenoh-{router_host}"
        out.mkdir()
        for f in (DEPLOY / "zenoh").glob("*.json5"):
            shutil.copy(f, out / f.name)
        shutil.copy(DEPLOY / "zenoh" / "users.txt.example", out / "users.txt")
        subprocess.run(["bash", str(DEPLOY / "gen-certs.sh"), str(out / "certs"), router_host],
                       check=True, capture_output=True, text=True)
        return out

    return make
