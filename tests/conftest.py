"""Fixtures shared by every test area: scene roots and real scene worker processes."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # so `from tests.helpers import ...` works under plain `pytest` too
    sys.path.insert(0, str(REPO))

from tests.helpers import free_port, start_worker, stop_process  # noqa: E402


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "worker: starts real scene worker processes (Zenoh, subprocesses)")


@pytest.fixture(scope="session")
def scene_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An empty folder to pass as a worker's ``--scene-root`` (generated scenes need no files)."""
    return tmp_path_factory.mktemp("scene_root")


@pytest.fixture(scope="module")
def worker_factory(scene_root: Path):
    """Start workers with ``worker_factory(run_id, shm=True, backend="raycast", **kw)``; each listens
    on a fresh loopback port (``proc.endpoint``) and is stopped when the module's tests end."""
    procs = []

    def start(run_id: str, shm: bool = True, backend: str = "raycast", **kw):
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        proc = start_worker(run_id, endpoint, kw.pop("scene_root", scene_root), backend=backend, shm=shm, **kw)
        proc.endpoint = endpoint
        procs.append(proc)
        return proc

    yield start
    for proc in procs:
        stop_process(proc)
