"""Cumulative wall-clock timings of a worker's stages, for health replies and step replies."""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Iterator


class StageTimer:
    """Accumulates how often each stage ran and how long it took in all.

    Stages are free-form names (``decode``, ``render``, ``query``, ``encode``, ``total``...).
    Not thread-safe: a worker runs its requests one at a time on one thread.
    """

    def __init__(self) -> None:
        self._count: dict[str, int] = {}
        self._total: dict[str, float] = {}

    def add(self, stage: str, seconds: float) -> None:
        """Record one run of ``stage`` that took ``seconds``."""
        self._count[stage] = self._count.get(stage, 0) + 1
        self._total[stage] = self._total.get(stage, 0.0) + float(seconds)

    @contextmanager
    def time(self, stage: str, into: dict[str, float] | None = None) -> Iterator[None]:
        """Time the body as one run of ``stage``; also add its seconds to ``into[stage + '_s']``."""
        start = time.perf_counter()
        try:
            yield
        finally:
            elapsed = time.perf_counter() - start
            self.add(stage, elapsed)
            if into is not None:
                into[f"{stage}_s"] = into.get(f"{stage}_s", 0.0) + elapsed

    def summary(self) -> dict[str, dict[str, float]]:
        """``{stage: {"count": int, "total_s": float}}`` since the worker started."""
        return {s: {"count": self._count[s], "total_s": self._total[s]} for s in sorted(self._count)}
