"""The delaying TCP proxy against a real echo server: added round trip, intact bytes, no serialised delays."""

from __future__ import annotations

import os
import socket
import statistics
import threading
import time

import pytest

from visfly_dist.bench.proxy import DelayProxy
from visfly_dist.errors import ConfigError


class EchoServer:
    """A threaded TCP echo server on a free loopback port."""

    def __init__(self) -> None:
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.address = self.listener.getsockname()
        self.threads: list[threading.Thread] = []
        self.received = 0  # bytes received so far, over all connections
        self.acceptor = threading.Thread(target=self._accept, daemon=True)
        self.acceptor.start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.listener.accept()
            except OSError:
                return
            t = threading.Thread(target=self._echo, args=(conn,), daemon=True)
            t.start()
            self.threads.append(t)

    def _echo(self, conn: socket.socket) -> None:
        with conn:
            while data := conn.recv(1 << 16):
                self.received += len(data)
                conn.sendall(data)
            conn.shutdown(socket.SHUT_WR)

    def close(self) -> None:
        self.listener.shutdown(socket.SHUT_RDWR)
        self.listener.close()
        self.acceptor.join(5)
        for t in self.threads:
            t.join(5)


@pytest.fixture
def echo():
    server = EchoServer()
    yield server
    server.close()


def connect(port: int) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=10)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return s


def recv_exactly(s: socket.socket, n: int) -> bytes:
    out = bytearray()
    while len(out) < n:
        chunk = s.recv(min(1 << 16, n - len(out)))
        assert chunk, f"connection closed after {len(out)} of {n} bytes"
        out += chunk
    return bytes(out)


def median_rtt(port: int, pings: int = 7) -> float:
    with connect(port) as s:
        rtts = []
        for i in range(pings):
            t0 = time.perf_counter()
            s.sendall(b"ping%03d" % i)
            assert recv_exactly(s, 7) == b"ping%03d" % i
            rtts.append(time.perf_counter() - t0)
    return statistics.median(rtts)


def test_round_trip_gains_the_delay(echo):
    direct = median_rtt(echo.address[1])
    with DelayProxy(echo.address, delay_ms=40) as proxy:
        proxied = median_rtt(proxy.port)
    # Each way waits until arrival + 20 ms, so the round trip can never be shorter than 40 ms (how
    # little longer it is on a given machine is for `visfly-dist bench`, not a unit test).
    assert proxied >= 0.040, (direct, proxied)


def test_zero_delay_forwards_bytes_intact_both_ways(echo):
    payload = os.urandom(3 << 20)
    with DelayProxy(echo.address, delay_ms=0) as proxy, connect(proxy.port) as s:
        sender = threading.Thread(target=s.sendall, args=(payload,))
        sender.start()
        got = recv_exactly(s, len(payload))
        sender.join()
        s.shutdown(socket.SHUT_WR)  # the half-close travels through: the echo server ends the stream
        assert s.recv(1) == b""
    assert got == payload


def test_delays_are_pipelined_not_serialised(echo):
    """Many chunks in flight each wait the delay once, from their own arrival: a burst of 40 writes has
    mostly reached the server by the time the first chunk's echo is back (one round trip). Serialised
    delays would have let through one chunk per one-way delay: 2 of the 40 by then."""
    delay_ms, writes, size = 1000, 40, 50_000
    payload = os.urandom(writes * size)
    with DelayProxy(echo.address, delay_ms=delay_ms) as proxy, connect(proxy.port) as s:
        def send() -> None:
            for i in range(writes):  # separate writes, so the proxy sees many chunks
                s.sendall(payload[i * size:(i + 1) * size])

        sender = threading.Thread(target=send)
        sender.start()
        first = recv_exactly(s, 1)
        at_first_echo = echo.received  # bytes the server had when the first echo came back
        got = first + recv_exactly(s, len(payload) - 1)
        sender.join()
    assert got == payload
    assert at_first_echo > len(payload) // 2, (at_first_echo, len(payload))


def test_close_ends_connections_and_threads(echo):
    proxy = DelayProxy(echo.address, delay_ms=10)
    s = connect(proxy.port)
    s.sendall(b"x")
    assert recv_exactly(s, 1) == b"x"
    proxy.close()
    proxy.close()  # idempotent
    assert s.recv(1) == b""  # the client sees the end of the stream
    s.close()
    assert not [t.name for t in threading.enumerate() if t.name.startswith("delay-proxy")]
    with pytest.raises(OSError):
        connect(proxy.port)


def test_unreachable_target_refuses_the_client():
    spare = socket.create_server(("127.0.0.1", 0))
    port = spare.getsockname()[1]
    spare.close()  # nothing listens there now
    with DelayProxy(("127.0.0.1", port), delay_ms=0) as proxy, connect(proxy.port) as s:
        assert s.recv(1) == b""


@pytest.mark.parametrize("delay", [-1, "5", 1e9])
def test_bad_delay_is_rejected(delay):
    with pytest.raises(ConfigError, match="delay_ms=.* must be a number of milliseconds"):
        DelayProxy(("127.0.0.1", 9), delay_ms=delay)
