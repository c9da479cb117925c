"""The thread count of PPO updates, chosen by timing the updates themselves.

During an update the local scene workers sit idle, so the update may use every CPU. On a machine
that other work keeps busy, more threads may not pay: a thread waits for the slowest at each
meeting point (once per minibatch, see :mod:`visfly_dist.training.parallel_update`; with OpenMP's
threads, after every operator, where 2 threads were measured 3-10x slower than one at a load
average of 6 on 2 cores). The load is not known in advance and changes during a run,
so :class:`UpdateThreadChooser` measures: it starts with the preferred candidate (every CPU), times
the others after 8 updates, keeps the fastest, and tries the others again now and then: twice as
long after each retiming that confirms the choice (up to 64 updates), and after 8 again when the
choice changes. The first timing of the others waits 8 updates because a split update degrades
gently under load (measured 1.9-5.4 s per update against 2.7-4.3 s on one thread, while OpenMP
threads took 8-14 s), so a short run does not pay for a slow one-thread update it rarely needs.
On a quiet machine the retimings cost a few percent of the update time; under outside load they
save most of it.
"""

from __future__ import annotations

from typing import Sequence

from visfly_dist.errors import ConfigError

REPROBE_EVERY = 8
"""Updates before the first retiming of another candidate (and after the choice changes)."""
MAX_REPROBE_EVERY = 64
"""The longest interval between retimings, reached by doubling while the choice holds."""


class UpdateThreadChooser:
    """Picks each update's thread count from the measured seconds of earlier updates (pure logic).

    Args:
        candidates: thread counts to choose from (distinct, >= 1), the preferred one first.
        reprobe_every: updates until a candidate other than the best is timed again (doubled while
            the choice holds, up to ``MAX_REPROBE_EVERY``).
    """

    def __init__(self, candidates: Sequence[int], reprobe_every: int = REPROBE_EVERY) -> None:
        self.candidates = tuple(dict.fromkeys(int(c) for c in candidates))
        if not self.candidates or min(self.candidates) < 1:
            raise ConfigError(f"thread candidates {list(candidates)} must be non-empty and >= 1")
        if reprobe_every < 2:
            raise ConfigError(f"reprobe_every={reprobe_every} must be >= 2")
        self.first_interval = self.interval = reprobe_every
        self.seconds: dict[int, float] = {}      # the latest update time of each candidate
        self.measured_at: dict[int, int] = {}    # the update count at that time
        self.updates = 0
        self._since_retiming = 0

    @property
    def best(self) -> int:
        """The candidate with the fastest latest update (the first candidate before any timing)."""
        timed = [c for c in self.candidates if c in self.seconds]
        return min(timed, key=lambda c: self.seconds[c]) if timed else self.candidates[0]

    def next(self) -> int:
        """Threads for the coming update."""
        if self.candidates[0] not in self.seconds:
            return self.candidates[0]
        best = self.best
        others = [c for c in self.candidates if c != best]
        if others and self._since_retiming >= self.interval:
            return min(others, key=lambda c: self.measured_at.get(c, -1))  # never timed first, then the stalest
        return best

    def record(self, threads: int, seconds: float) -> None:
        """The update just run with ``threads`` took ``seconds``."""
        before = self.best
        retiming = threads != before
        self.updates += 1
        self.seconds[threads] = float(seconds)
        self.measured_at[threads] = self.updates
        self._since_retiming += 1
        if retiming:
            self._since_retiming = 0
            self.interval = (self.first_interval if self.best != before
                             else min(2 * self.interval, max(MAX_REPROBE_EVERY, self.first_interval)))
