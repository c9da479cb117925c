"""Requests lost by workers that are alive: whose fault it is, and when to stop replacing workers.

A request that gets no answer usually means a dead or hung worker, which the pool replaces. When
the worker still answers a small health probe, it is alive and reachable, and what failed is the
delivery of requests of that size. If no worker answers such requests, replacing workers cannot
help: the fault is on the learner's side (its Zenoh shared memory broken, for example), and every
replacement would time out the same way, one step timeout after another. This module keeps the
tally and decides; it does no I/O (the pool probes and acts).

The rules, with ``limit`` = ``PoolConfig.lost_request_limit``:
- each lost-but-alive request counts once for the run and once for its worker, and the smallest
  such request size is remembered;
- an answer to a request at least that large resets the run's tally (requests of that size do
  arrive), and the answering worker's own tally;
- the run's tally reaching ``limit`` fails the run (:attr:`Verdict.FAIL`); a worker's own tally
  reaching it while others do answer means that worker is at fault: replace it
  (:attr:`Verdict.REPLACE`); otherwise keep it (:attr:`Verdict.KEEP`).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum


class Verdict(Enum):
    """What to do with a worker that lost a request but answered the probe."""

    KEEP = "keep"        # alive; the fault may be elsewhere: do not kill it yet
    REPLACE = "replace"  # others answer requests of this size and it does not: its own fault
    FAIL = "fail"        # nobody answers requests of this size: the learner's side is at fault


@dataclass
class _Tally:
    count: int = 0
    smallest: int = 0


class LostRequests:
    """The tally of lost-but-alive requests of one run.

    Args:
        limit: consecutive lost-but-alive requests after which the run fails (>= 1).
    """

    def __init__(self, limit: int) -> None:
        assert limit >= 1, limit
        self.limit = limit
        self._run = _Tally()
        self._workers: dict[str, _Tally] = {}

    @property
    def count(self) -> int:
        """Lost-but-alive requests since a request of that size was last answered."""
        return self._run.count

    def answered(self, worker_id: str, request_bytes: int) -> None:
        """``worker_id`` answered a request of ``request_bytes`` (an error reply counts: it arrived)."""
        if self._run.count and request_bytes >= self._run.smallest:
            self._run = _Tally()
        mine = self._workers.get(worker_id)
        if mine is not None and request_bytes >= mine.smallest:
            del self._workers[worker_id]

    def lost_but_alive(self, worker_id: str, request_bytes: int) -> Verdict:
        """Count a request of ``request_bytes`` that ``worker_id`` did not answer although it answers probes."""
        for tally in (self._run, self._workers.setdefault(worker_id, _Tally())):
            tally.smallest = min(tally.smallest, request_bytes) if tally.count else request_bytes
            tally.count += 1
        if self._run.count >= self.limit:
            return Verdict.FAIL
        if self._workers[worker_id].count >= self.limit:
            del self._workers[worker_id]
            return Verdict.REPLACE
        return Verdict.KEEP

    def forget(self, worker_id: str) -> None:
        """The worker was dropped or left: its own tally goes (the run's stays)."""
        self._workers.pop(worker_id, None)
