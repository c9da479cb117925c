"""Remote scene workers behind an added network delay, on this host, for the latency benchmarks.

The trainer's aggregator listens on a loopback TCP port ``P`` (``PoolConfig(listen=(tcp P,),
num_local_workers=0, shared_memory=False)``); a :class:`~visfly_dist.bench.proxy.DelayProxy`, in a
process of its own so that its threads take no GIL time from the measured process, forwards to
``P``; and ``visfly-dist worker --connect tcp/127.0.0.1:<proxy port> --no-shm``
processes are started pointed at the proxy, exactly as a user starts workers on other hosts. Every
byte between the aggregator and its workers then pays the proxy's delay.

A Zenoh client fails at once when its endpoint does not answer, and the aggregator only listens
once the env is being built, so the workers are started by a background thread as soon as ``P``
shows up as a listening socket in ``/proc/net/tcp``.
"""

from __future__ import annotations

import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace
from typing import Any

from visfly_dist.errors import ConfigError

_TCP_LISTEN = "0A"


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def is_listening(port: int) -> bool:
    """Whether some socket of this host listens on TCP ``port`` (Linux ``/proc/net/tcp``)."""
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            with open(table) as f:
                next(f)
                for line in f:
                    fields = line.split()
                    if fields[3] == _TCP_LISTEN and int(fields[1].rsplit(":", 1)[1], 16) == port:
                        return True
        except OSError:
            continue
    return False


def start_proxy(target_port: int, delay_ms: float, timeout_s: float = 30.0) -> tuple[subprocess.Popen, str]:
    """Start ``python -m visfly_dist.bench.proxy`` forwarding to ``127.0.0.1:target_port``.

    Returns:
        The process and the proxy's endpoint ``tcp/127.0.0.1:PORT``.

    Raises:
        ConfigError: a bad delay (the proxy's own message).
        RuntimeError: the proxy did not report its port within ``timeout_s``.
    """
    if not isinstance(delay_ms, (int, float)) or not 0 <= delay_ms <= 60_000:
        raise ConfigError(f"delay_ms={delay_ms!r} must be a number of milliseconds in [0, 60000]")
    argv = [sys.executable, "-m", "visfly_dist.bench.proxy", "--target", f"127.0.0.1:{target_port}",
            "--delay-ms", str(delay_ms)]
    proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            start_new_session=True)
    stdout = proc.stdout
    assert stdout is not None  # stdout=PIPE
    ready, _, _ = select.select([stdout], [], [], timeout_s)
    line = stdout.readline().decode(errors="replace").strip() if ready else ""
    prefix = "delay proxy listening on "
    if not line.startswith(prefix):
        proc.kill()
        rest = proc.communicate()[0].decode(errors="replace")
        stdout.close()
        raise RuntimeError(f"the delay proxy did not start within {timeout_s} s: {line}{rest}"[-2000:])
    return proc, line[len(prefix):]


class RemoteWorkers:
    """``count`` worker processes reaching the trainer through a :class:`DelayProxy`.

    Args:
        count: worker processes.
        delay_ms: added round trip between the aggregator and every worker.
        backend: the workers' renderer.
        run_id: the run's key namespace (default: a fresh one).
        start_timeout_s: how long to wait for the aggregator to listen before giving up.

    Use :meth:`pool` to build the trainer's ``PoolConfig``, build the env (that makes the
    aggregator listen; the workers start then), and :meth:`close` (or ``with``) afterwards.
    """

    def __init__(self, count: int, delay_ms: float, backend: str = "raycast", run_id: str | None = None,
                 start_timeout_s: float = 120.0) -> None:
        if not isinstance(count, int) or count < 1:
            raise ConfigError(f"count={count!r} remote workers must be an int >= 1")
        self.count = count
        self.backend = backend
        self.run_id = run_id or f"bench{os.getpid()}x{int(time.time() * 1000) % 100000}"
        self.listen_port = free_port()
        self._proxy, self.proxy_endpoint = start_proxy(self.listen_port, delay_ms)
        self._log_dir = tempfile.mkdtemp(prefix=f"visfly-{self.run_id}-")
        self._processes: list[subprocess.Popen] = []
        self._closed = threading.Event()
        self._start_timeout_s = start_timeout_s
        self._starter = threading.Thread(target=self._start_when_listening, daemon=True, name="bench-remote-start")
        self._starter.start()

    def pool(self, base: Any) -> Any:
        """``base`` (a ``PoolConfig``) changed to take only these workers, over plain TCP."""
        return replace(base, run_id=self.run_id, listen=(f"tcp/127.0.0.1:{self.listen_port}",), connect=(),
                       num_local_workers=0, shared_memory=False, min_workers=self.count)

    def argv(self, index: int) -> list[str]:
        """The command line of worker ``index``: a remote worker pointed at the proxy."""
        return [sys.executable, "-m", "visfly_dist.cli", "worker", "--run-id", self.run_id, "--connect",
                self.proxy_endpoint, "--no-shm", "--backend", self.backend, "--worker-id", f"remote-{index}",
                "--parent-pid", str(os.getpid())]

    def _start_when_listening(self) -> None:
        deadline = time.monotonic() + self._start_timeout_s
        while not is_listening(self.listen_port):
            if self._closed.is_set() or time.monotonic() > deadline:
                return
            time.sleep(0.05)
        for i in range(self.count):
            if self._closed.is_set():
                return
            with open(os.path.join(self._log_dir, f"remote-{i}.log"), "ab") as log:
                self._processes.append(subprocess.Popen(self.argv(i), stdin=subprocess.DEVNULL, stdout=log,
                                                        stderr=subprocess.STDOUT, start_new_session=True))

    def log_tail(self, max_chars: int = 1500) -> str:
        """The end of every worker's log, for error messages."""
        out = []
        for name in sorted(os.listdir(self._log_dir)):
            with open(os.path.join(self._log_dir, name), "rb") as f:
                out.append(f"{name}: {f.read()[-max_chars:].decode(errors='replace').strip()}")
        return "\n".join(out)

    def close(self, grace_s: float = 5.0) -> None:
        """Stop the workers (SIGTERM, then SIGKILL after ``grace_s``), then the proxy. Idempotent."""
        if self._closed.is_set():
            return
        self._closed.set()
        self._starter.join()
        for p in self._processes:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        for p in self._processes:
            try:
                p.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self._proxy.terminate()
        try:
            self._proxy.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            self._proxy.kill()
            self._proxy.wait()
        if self._proxy.stdout is not None:  # start_proxy reads its stdout (a pipe)
            self._proxy.stdout.close()
        shutil.rmtree(self._log_dir, ignore_errors=True)

    def __enter__(self) -> "RemoteWorkers":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
