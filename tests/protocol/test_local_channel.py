"""The local channel between a trainer and a worker it started: framing, matching, expiry, a closed end."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

from tests.helpers import REPO
from visfly_dist.aggregator.config import PoolConfig
from visfly_dist.aggregator.pool import WorkerPool
from visfly_dist.errors import ConfigError
from visfly_dist.protocol.codec import PROTOCOL_VERSION
from visfly_dist.protocol.local_channel import (
    HEADER, OK, TIMEOUT_PAYLOAD, ChannelClient, ChannelRequest, ChannelServer, socket_pair,
)
from visfly_dist.protocol.messages import Health
from visfly_dist.scene_worker.cli import inherited_socket


class Waiter:
    """Records every finish (there must be exactly one)."""

    def __init__(self) -> None:
        self.results: list[tuple[bool, bytes] | None] = []
        self.finished = threading.Event()

    def finish(self, raw: tuple[bool, bytes] | None) -> None:
        self.results.append(raw)
        self.finished.set()

    def wait(self, timeout_s: float = 5.0) -> tuple[bool, bytes] | None:
        assert self.finished.wait(timeout_s), "never finished"
        return self.results[0]


@pytest.fixture
def channel():
    """A client and the requests its server end received (answered by the test)."""
    ours, theirs = socket_pair()
    inbox: list[ChannelRequest] = []
    arrived = threading.Condition()

    def deliver(request: ChannelRequest) -> None:
        with arrived:
            inbox.append(request)
            arrived.notify_all()

    def wait_for(count: int) -> list[ChannelRequest]:
        with arrived:
            assert arrived.wait_for(lambda: len(inbox) >= count, timeout=5.0), inbox
            return list(inbox)

    client = ChannelClient(ours, "test")
    server = ChannelServer(theirs, deliver)
    yield client, server, wait_for
    client.close()
    server.close()


def test_replies_reach_their_own_requests_in_any_order(channel):
    client, _, wait_for = channel
    waiters = [Waiter() for _ in range(3)]
    for i, waiter in enumerate(waiters):
        client.send(f"request {i}".encode(), waiter, timeout_s=5.0)
    requests = wait_for(3)
    assert [r.payload for r in requests] == [b"request 0", b"request 1", b"request 2"]
    for request in reversed(requests):  # the worker answers the last first
        request.respond(request.payload != b"request 1", b"answer to " + request.payload)
    assert [w.wait() for w in waiters] == [(True, b"answer to request 0"), (False, b"answer to request 1"),
                                           (True, b"answer to request 2")]
    assert all(len(w.results) == 1 for w in waiters)


def test_large_payloads_cross_intact_both_ways(channel):
    client, _, wait_for = channel
    body = os.urandom(8 * 1024 * 1024 + 3)
    waiter = Waiter()
    client.send(body, waiter, timeout_s=10.0)
    (request,) = wait_for(1)
    assert request.payload == body
    request.respond(True, body[::-1])
    assert waiter.wait(10.0) == (True, body[::-1])


def test_an_unanswered_request_expires_as_a_zenoh_query_does_and_a_late_reply_is_dropped(channel):
    client, _, wait_for = channel
    waiter = Waiter()
    t0 = time.monotonic()
    client.send(b"slow", waiter, timeout_s=0.3)
    assert waiter.wait() == (False, TIMEOUT_PAYLOAD)
    assert 0.3 <= time.monotonic() - t0 < 1.5
    (request,) = wait_for(1)
    request.respond(True, b"too late")
    answered = Waiter()
    client.send(b"next", answered, timeout_s=5.0)  # the channel still works after the late reply
    wait_for(2)[1].respond(True, b"in time")
    assert answered.wait() == (True, b"in time")
    assert waiter.results == [(False, TIMEOUT_PAYLOAD)]


def test_a_closed_worker_end_fails_requests_in_flight_at_once_and_later_ones_too(channel):
    client, server, wait_for = channel
    waiter = Waiter()
    client.send(b"held", waiter, timeout_s=30.0)
    wait_for(1)
    t0 = time.monotonic()
    server.close()  # what the worker's death does to its end
    assert waiter.wait() is None
    assert time.monotonic() - t0 < 1.0
    later = Waiter()
    client.send(b"after", later, timeout_s=30.0)
    assert later.wait(1.0) is None


def test_a_frame_beyond_the_message_bound_closes_the_channel():
    ours, theirs = socket_pair()
    client = ChannelClient(ours, "test")
    try:
        waiter = Waiter()
        client.send(b"x", waiter, timeout_s=30.0)
        theirs.sendall(HEADER.pack(1, 2**40, OK))  # a length no message may have
        assert waiter.wait() is None
    finally:
        client.close()
        theirs.close()


def test_channel_fd_must_be_an_inherited_unix_stream_socket():
    read_end, write_end = os.pipe()
    try:
        with pytest.raises(ConfigError, match="--channel-fd"):
            inherited_socket(read_end)
    finally:
        os.close(read_end)
        os.close(write_end)
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        with pytest.raises(ConfigError, match="Unix stream socket"):
            inherited_socket(udp.fileno())
        assert udp.fileno() >= 0  # refused, not taken over
    finally:
        udp.close()


@pytest.mark.parametrize("local_channel", [True, False])
def test_a_local_worker_answers_over_either_transport(local_channel):
    pool = WorkerPool(PoolConfig(num_local_workers=1, backend="raycast", local_channel=local_channel, lease_ms=1000),
                      f"chan{os.getpid()}{int(local_channel)}")
    pool.open()
    try:
        (wid,) = pool.wait_for(1, 60.0)
        (reply,) = pool.call([(wid, Health().to_message())], timeout_s=10.0)
        assert reply.message is not None and reply.message["version"] == PROTOCOL_VERSION, reply
        assert reply.message["worker_id"] == wid and reply.message["pid"] == pool.local_pids()[wid]
        assert pool.transport(wid) == ("channel" if local_channel else "zenoh")
        # a bad request gets the same error reply whatever carried it, and the worker serves on
        (bad,) = pool.call([(wid, {"version": PROTOCOL_VERSION, "type": "no-such-request"})], timeout_s=10.0)
        assert bad.error is not None and bad.error.error_type == "ProtocolError", bad
        (again,) = pool.call([(wid, Health().to_message())], timeout_s=10.0)
        assert again.message is not None and again.message["pid"] == pool.local_pids()[wid], again
    finally:
        pool.close()


def test_a_request_to_a_worker_killed_while_it_holds_it_fails_at_once_on_the_channel():
    pool = WorkerPool(PoolConfig(num_local_workers=1, backend="raycast", lease_ms=10_000, respawn=False),
                      f"chankill{os.getpid()}")
    pool.open()
    try:
        (wid,) = pool.wait_for(1, 60.0)
        pid = pool.local_pids()[wid]
        os.kill(pid, signal.SIGSTOP)  # it cannot answer; its Zenoh lease (10 s) keeps its token
        (pending,) = pool.send([(wid, Health().to_message())], timeout_s=30.0)
        time.sleep(0.2)
        assert not pending.done()
        t0 = time.monotonic()
        os.kill(pid, signal.SIGKILL)
        assert pool.wait_any([[pending]], 5.0) == 0
        assert time.monotonic() - t0 < 1.0
        reply = pool.result(pending)
        assert reply.message is None and "no reply" in reply.failure, reply
    finally:
        pool.close()


def test_a_request_to_a_gone_worker_fails_without_sigpipe_even_where_it_is_not_ignored():
    script = r"""
import signal, time
from visfly_dist.protocol.local_channel import ChannelClient, socket_pair
signal.signal(signal.SIGPIPE, signal.SIG_DFL)  # what a CLI that pipes its output may restore
ours, theirs = socket_pair()
client = ChannelClient(ours, "gone")
theirs.close()
got = []
class Waiter:
    def finish(self, raw):
        got.append(raw)
for _ in range(3):
    client.send(b"x" * 100_000, Waiter(), timeout_s=5.0)
deadline = time.monotonic() + 5.0
while len(got) < 3 and time.monotonic() < deadline:
    time.sleep(0.01)
print(got)
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60,
                          env={**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))})
    assert done.returncode == 0 and done.stdout.strip() == "[None, None, None]", (done.returncode, done.stdout, done.stderr)
