"""The pool's requests over a real Zenoh session: a request is done at its reply, before the query ends."""

from __future__ import annotations

import os
import queue
import time

import zenoh

from tests.helpers import client_session, free_port
from visfly_dist.aggregator.config import PoolConfig
from visfly_dist.aggregator.pool import WorkerPool
from visfly_dist.protocol import keys
from visfly_dist.protocol.codec import PROTOCOL_VERSION, decode, encode
from visfly_dist.protocol.messages import Health

RUN = f"pool{os.getpid()}"


def test_a_request_is_done_at_its_reply_though_the_worker_holds_the_query():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    pool = WorkerPool(PoolConfig(num_local_workers=0, listen=(endpoint,)), RUN)
    pool.open()
    held: queue.SimpleQueue = queue.SimpleQueue()

    def answer_but_hold(query) -> None:  # replies at once, drops the query (its final message) only later
        held.put(query)  # before the reply: the test may look at ``held`` as soon as the reply is in
        query.reply(keys.worker_rpc(RUN, "w0"), encode({"type": "echo", "got": decode(query.payload.to_bytes())["type"]}))

    try:
        with client_session(endpoint) as session:
            queryable = session.declare_queryable(keys.worker_rpc(RUN, "w0"),
                                                  zenoh.handlers.Callback(answer_but_hold, indirect=False))
            # Until the queryable is seen: before that, a get finds no one and ends at once with no
            # reply, so tries are bounded by time (discovery can take seconds on a loaded host), not count.
            deadline = time.monotonic() + 30.0
            while True:
                (pending,) = pool.send([("w0", Health().to_message())], timeout_s=5.0)
                pool.wait_any([[pending]], 2.0)
                # done() as well as the bytes: Zenoh's thread keeps the bytes just before it flags the
                # request done, so a wait that times out in between sees the one without the other
                if (pending.done() and pending.raw is not None) or time.monotonic() > deadline:
                    break
                time.sleep(0.05)
            assert pending.done()
            reply = pool.result(pending)
            assert reply.message == {"version": PROTOCOL_VERSION, "type": "echo", "got": "health"}, reply
            assert not held.empty()  # the query is still open: done() came from the reply itself
            while not held.empty():
                held.get().drop()
            queryable.undeclare()
    finally:
        pool.close()
