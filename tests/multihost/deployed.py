"""A working copy of the shipped Zenoh configs (``deploy/zenoh``) with fresh certificates."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def copy_deploy_configs(folder: Path, router_host: str) -> Path:
    """Copy every ``deploy/zenoh/*.json5`` into ``folder``, with ``users.txt`` from the example and
    ``certs/`` made by ``deploy/gen-certs.sh`` for ``router_host``; returns ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    for f in (DEPLOY / "zenoh").glob("*.json5"):
        shutil.copy(f, folder / f.name)
    shutil.copy(DEPLOY / "zenoh" / "users.txt.example", folder / "users.txt")
    subprocess.run(["bash", str(DEPLOY / "gen-certs.sh"), str(folder / "certs"), router_host],
                   check=True, capture_output=True, text=True)
    return folder
