"""Helpers for tests that run real scene worker processes and talk to them over Zenoh.

Usage::

    from tests.helpers import free_port, start_worker, stop_process, client_session, call

    port = free_port()
    proc = start_worker("run1", f"tcp/127.0.0.1:{port}", scene_root, backend="raycast")
    try:
        with client_session(f"tcp/127.0.0.1:{port}") as s:
            ok, reply = call(s, proc.rpc_key, Health().to_message())
    finally:
        stop_process(proc)
"""

from __future__ import annotations

import os
import selectors
import signal
import socket
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import pytest

REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def worker_argv(run_id: str, endpoint: str, scene_root: str | os.PathLike, backend: str = "raycast",
                shm: bool = True, worker_id: str | None = None, connect: bool = False,
                extra_args: Sequence[str] = ()) -> list[str]:
    """The command line of a worker that listens on ``endpoint`` (or connects to it if ``connect``)."""
    argv = [sys.executable, "-m", "visfly_dist.cli", "worker", "--run-id", run_id,
            "--connect" if connect else "--listen", endpoint, "--scene-root", str(scene_root), "--backend", backend]
    if worker_id is not None:
        argv += ["--worker-id", worker_id]
    if not shm:
        argv.append("--no-shm")
    return argv + list(extra_args)


def start_worker(run_id: str, endpoint: str, scene_root: str | os.PathLike, backend: str = "raycast",
                 shm: bool = True, worker_id: str | None = None, connect: bool = False,
                 extra_args: Sequence[str] = (), timeout: float = 60.0) -> subprocess.Popen:
    """Start ``visfly-dist worker`` and wait for its ready line.

    The returned Popen also carries ``worker_id``, ``rpc_key``, ``alive_key`` and
    ``stderr_text()`` (the worker's log so far). Raises RuntimeError with the worker's stderr if it
    exits or is not ready within ``timeout`` seconds.
    """
    from visfly_dist.protocol import keys

    worker_id = worker_id or f"w{free_port()}"
    err = tempfile.TemporaryFile(mode="w+b")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    proc = subprocess.Popen(worker_argv(run_id, endpoint, scene_root, backend, shm, worker_id, connect, extra_args),
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=err, env=env, cwd=REPO)

    def stderr_text() -> str:
        err.seek(0)
        return err.read().decode(errors="replace")

    proc.worker_id, proc.stderr_text = worker_id, stderr_text
    proc.rpc_key, proc.alive_key = keys.worker_rpc(run_id, worker_id), keys.worker_alive(run_id, worker_id)
    line = _read_line(proc, timeout)
    if f"worker {worker_id} ready" not in line:
        stop_process(proc)
        raise RuntimeError(f"worker did not get ready (stdout {line!r}, exit {proc.returncode}):\n{stderr_text()}")
    return proc


def _read_line(proc: subprocess.Popen, timeout: float) -> str:
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        if not sel.select(timeout):
            return ""
    return proc.stdout.readline().decode(errors="replace")


def stop_process(proc: subprocess.Popen, sig: int = signal.SIGTERM, timeout: float = 15.0) -> int:
    """Send ``sig``, wait up to ``timeout`` s (then SIGKILL), close its pipes; returns the exit code."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    if proc.stdout is not None:
        proc.stdout.close()
    return proc.returncode


@contextmanager
def client_session(endpoint: str, shm: bool = True) -> Iterator[Any]:
    """A Zenoh client session connected to ``endpoint``, closed on exit."""
    from visfly_dist.protocol.session import client_of, open_session

    session = open_session(client_of([endpoint], shared_memory=shm))
    try:
        yield session
    finally:
        session.close()


def call(session: Any, key: str, message: Mapping[str, Any] | bytes, timeout: float = 30.0) -> tuple[bool, dict]:
    """Send one request; return ``(ok, decoded reply)``. Exactly one reply must come back."""
    import zenoh

    from visfly_dist.protocol.codec import decode, encode

    payload = message if isinstance(message, bytes) else encode(message)
    replies = list(session.get(key, payload=payload, timeout=timeout, consolidation=zenoh.ConsolidationMode.NONE))
    assert len(replies) == 1, f"expected one reply from {key}, got {len(replies)}"
    reply = replies[0]
    if reply.ok is not None:
        return True, decode(reply.ok.payload.to_bytes())
    return False, decode(reply.err.payload.to_bytes())


def wait_for(predicate, timeout: float = 10.0, interval: float = 0.01) -> bool:
    """Poll ``predicate()`` until it is true or ``timeout`` seconds pass; returns its last value."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(interval)
    return True


@contextmanager
def native_switched_off(variable: str, loader: Any) -> Iterator[None]:
    """A native library switched off by its ``variable`` (set to ``0``) while the block runs; its cached
    loading (``loader``, an ``lru_cache``d function) forgotten before and after, so each side loads anew."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(variable, "0")
        loader.cache_clear()
        try:
            yield
        finally:
            loader.cache_clear()
    loader.cache_clear()
