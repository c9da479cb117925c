"""A delaying TCP proxy: emulated network latency for benchmarks (``tc netem`` is not available here).

``DelayProxy`` listens on a loopback port and forwards every connection to a target. Every chunk
read in either direction is held ``delay_ms / 2`` before it is written on, so a request and its
reply pay ``delay_ms`` of added round trip, as two hosts that far apart would.

The delays are not serialised. Each direction of a connection has two threads and a queue between
them: the reader stamps each chunk with the time it is due (arrival + one-way delay) and queues it
without waiting; the writer sleeps until the oldest chunk is due, then sends it. Every chunk waits
the same one-way delay counted from its own arrival, so a stream of chunks arrives as a stream,
shifted by the delay: throughput is what the copying allows, not one chunk per delay.

A half-close travels with the data: when one side stops sending, the other side sees the end of
the stream after the chunks before it (also delayed). ``close()`` stops accepting, shuts every
connection down and joins every thread; it is idempotent, and the proxy is a context manager.
"""

from __future__ import annotations

import collections
import socket
import threading
import time
from typing import Deque

from visfly_dist.errors import ConfigError

CHUNK_BYTES = 1 << 16
_EOF = b""


class _Pipe:
    """One direction of one connection: read from ``src``, write to ``dst`` ``one_way_s`` later."""

    def __init__(self, src: socket.socket, dst: socket.socket, one_way_s: float, done: threading.Event) -> None:
        self.src, self.dst, self.one_way_s = src, dst, one_way_s
        self._queue: Deque[tuple[float, bytes]] = collections.deque()
        self._ready = threading.Condition()
        self._done = done
        self.threads = (threading.Thread(target=self._read, daemon=True, name="delay-proxy-read"),
                        threading.Thread(target=self._write, daemon=True, name="delay-proxy-write"))

    def start(self) -> None:
        for t in self.threads:
            t.start()

    def _push(self, chunk: bytes) -> None:
        with self._ready:
            self._queue.append((time.monotonic() + self.one_way_s, chunk))
            self._ready.notify()

    def _read(self) -> None:
        try:
            while chunk := self.src.recv(CHUNK_BYTES):
                self._push(chunk)
        except OSError:  # the socket was shut down (close()) or reset by a peer
            pass
        self._push(_EOF)

    def _write(self) -> None:
        while True:
            with self._ready:
                while not self._queue and not self._done.is_set():
                    self._ready.wait(0.5)
                if not self._queue:  # closed with nothing left to deliver
                    return
                due, chunk = self._queue.popleft()
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            try:
                if not chunk:
                    self.dst.shutdown(socket.SHUT_WR)
                    return
                self.dst.sendall(chunk)
            except OSError:
                return

    def wake(self) -> None:
        with self._ready:
            self._ready.notify_all()


class _Connection:
    """A client socket, its upstream socket, and the two delayed pipes between them."""

    def __init__(self, client: socket.socket, upstream: socket.socket, one_way_s: float) -> None:
        self.sockets = (client, upstream)
        self.done = threading.Event()
        self.pipes = (_Pipe(client, upstream, one_way_s, self.done), _Pipe(upstream, client, one_way_s, self.done))
        for p in self.pipes:
            p.start()

    def finished(self) -> bool:
        return not any(t.is_alive() for p in self.pipes for t in p.threads)

    def close(self, timeout_s: float) -> None:
        self.done.set()
        for s in self.sockets:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        for p in self.pipes:
            p.wake()
        for p in self.pipes:
            for t in p.threads:
                t.join(timeout_s)
        for s in self.sockets:
            s.close()


class DelayProxy:
    """Forward ``127.0.0.1:<port>`` to ``target``, adding ``delay_ms`` of round trip.

    Args:
        target: ``(host, port)`` every accepted connection is forwarded to.
        delay_ms: added round trip in milliseconds (``delay_ms / 2`` each way), >= 0.
        port: port to listen on (0: a free one; see :attr:`port`).
        host: address to listen on.

    Example::

        with DelayProxy(("127.0.0.1", 7447), delay_ms=20) as proxy:
            ...  # connect to ("127.0.0.1", proxy.port)
    """

    def __init__(self, target: tuple[str, int], delay_ms: float, *, port: int = 0, host: str = "127.0.0.1") -> None:
        if not isinstance(delay_ms, (int, float)) or not 0 <= delay_ms <= 60_000:
            raise ConfigError(f"delay_ms={delay_ms!r} must be a number of milliseconds in [0, 60000]")
        self.target = (str(target[0]), int(target[1]))
        self.delay_ms = float(delay_ms)
        self._listener = socket.create_server((host, port))
        self.host, self.port = self._listener.getsockname()[:2]
        self._connections: list[_Connection] = []
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._acceptor = threading.Thread(target=self._accept, daemon=True, name="delay-proxy-accept")
        self._acceptor.start()

    @property
    def endpoint(self) -> str:
        """The proxy's Zenoh endpoint, ``tcp/HOST:PORT``."""
        return f"tcp/{self.host}:{self.port}"

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                client, _ = self._listener.accept()
            except OSError:  # the listener was closed
                return
            try:
                upstream = socket.create_connection(self.target, timeout=10.0)
            except OSError:
                client.close()  # the target is down: the client sees the connection refused, as it would directly
                continue
            upstream.settimeout(None)
            for s in (client, upstream):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                if self._closed.is_set():
                    client.close()
                    upstream.close()
                    return
                for c in [c for c in self._connections if c.finished()]:
                    c.close(0.0)
                    self._connections.remove(c)
                self._connections.append(_Connection(client, upstream, self.delay_ms / 2e3))

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop accepting, end every connection, join every thread. Idempotent."""
        if self._closed.is_set():
            return
        self._closed.set()
        try:
            self._listener.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._listener.close()
        self._acceptor.join(timeout_s)
        with self._lock:
            connections, self._connections = self._connections, []
        for c in connections:
            c.close(timeout_s)

    def __enter__(self) -> "DelayProxy":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def main(argv: list[str] | None = None) -> int:
    """``python -m visfly_dist.bench.proxy --target HOST:PORT --delay-ms D``: run a proxy in its own
    process (so its threads never compete with the measured process for the GIL) until SIGTERM/SIGINT.

    Prints ``delay proxy listening on tcp/HOST:PORT`` once it accepts connections, and exits by
    itself when its parent process is gone.
    """
    import argparse
    import os
    import signal

    parser = argparse.ArgumentParser(prog="python -m visfly_dist.bench.proxy", description=__doc__.splitlines()[0])
    parser.add_argument("--target", required=True, metavar="HOST:PORT", help="where connections are forwarded")
    parser.add_argument("--delay-ms", type=float, required=True, help="added round trip, ms")
    parser.add_argument("--port", type=int, default=0, help="port to listen on (0: a free one)")
    args = parser.parse_args(argv)
    host, sep, port = args.target.rpartition(":")
    if not sep or not port.isdigit():
        raise ConfigError(f"--target {args.target!r} must look like HOST:PORT, e.g. 127.0.0.1:7447")
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    parent = os.getppid()
    with DelayProxy((host, int(port)), args.delay_ms, port=args.port) as proxy:
        print(f"delay proxy listening on {proxy.endpoint}", flush=True)
        while not stop.wait(0.5) and os.getppid() == parent:
            pass
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
