"""Start and stop scene worker processes on this host.

Workers are started with ``subprocess`` (fork + immediate exec, no Python runs in the child), so
it is safe even after this process opened a Zenoh session; ``fork`` alone is not (a forked Zenoh session hangs).
Each worker gets ``--parent-pid`` so it exits by itself if its parent dies, and runs in its own
session so a Ctrl-C in the terminal reaches the parent only, which then stops its workers.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from typing import Iterable, Sequence


@dataclass(frozen=True)
class WorkerLaunchSpec:
    """What every local worker of a pool is started with.

    Attributes:
        run_id: run namespace.
        connect: endpoints the worker connects to (client mode).
        scene_roots: folders the worker may load scene files from.
        backend: ``auto``, ``egl`` or ``raycast``.
        shared_memory: ``False`` adds ``--no-shm``.
        lease_ms: the worker-side link lease (bounds hang detection).
        parent_pid: the worker exits when this process is gone (``None``: never).
        threads: tracing threads of each worker (``None``: the worker's default).
        zenoh_config: absolute path of a Zenoh JSON5 config file (TLS, credentials), or ``None``.
    """

    run_id: str
    connect: tuple[str, ...]
    scene_roots: tuple[str, ...] = ()
    backend: str = "auto"
    shared_memory: bool = True
    lease_ms: int = 2000
    parent_pid: int | None = None
    threads: int | None = None
    zenoh_config: str | None = None

    def argv(self, worker_id: str, channel_fd: int | None = None) -> list[str]:
        """The command line of worker ``worker_id``; ``channel_fd``: its end of a local channel, inherited."""
        argv = [sys.executable, "-m", "visfly_dist.cli", "worker", "--run-id", self.run_id,
                "--worker-id", worker_id, "--backend", self.backend, "--lease-ms", str(self.lease_ms)]
        for ep in self.connect:
            argv += ["--connect", ep]
        for root in self.scene_roots:
            argv += ["--scene-root", os.path.abspath(root)]
        if not self.shared_memory:
            argv.append("--no-shm")
        if self.parent_pid is not None:
            argv += ["--parent-pid", str(self.parent_pid)]
        if self.threads is not None:
            argv += ["--threads", str(self.threads)]
        if self.zenoh_config is not None:
            argv += ["--zenoh-config", self.zenoh_config]
        if channel_fd is not None:
            argv += ["--channel-fd", str(channel_fd)]
        return argv


class LocalWorker:
    """One worker process; its stdout and stderr go to ``log_path``; it inherits ``pass_fds``."""

    def __init__(self, worker_id: str, argv: Sequence[str], log_path: str, pass_fds: Sequence[int] = ()) -> None:
        self.worker_id = worker_id
        self.log_path = log_path
        self.started_at = time.monotonic()
        with open(log_path, "ab") as log:
            self.process = subprocess.Popen(
                list(argv), stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                close_fds=True, pass_fds=tuple(pass_fds), start_new_session=True,
            )

    @property
    def pid(self) -> int:
        return self.process.pid

    def running(self) -> bool:
        return self.process.poll() is None

    def kill(self) -> None:
        """SIGKILL now (a hung worker), and reap it."""
        if self.running():
            self.process.kill()
        self.process.wait()

    def log_tail(self, max_chars: int = 2000) -> str:
        """The end of the worker's output, for error messages."""
        try:
            with open(self.log_path, "rb") as f:
                f.seek(0, os.SEEK_END)
                f.seek(max(0, f.tell() - max_chars))
                return f.read().decode(errors="replace").strip()
        except OSError:
            return ""


def stop_workers(workers: Iterable[LocalWorker], grace_s: float = 5.0) -> None:
    """SIGTERM every worker at once, wait up to ``grace_s`` for all, then SIGKILL the rest."""
    workers = list(workers)
    for w in workers:
        if w.running():
            try:
                w.process.send_signal(signal.SIGTERM)
            except ProcessLookupError:
                pass
    deadline = time.monotonic() + grace_s
    for w in workers:
        try:
            w.process.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            w.kill()
