"""How a worker runs the heavy half of its loads: how many at once, on which threads, in which processes.

The serving thread accepts a load (:meth:`SceneLoader.add`), starts the loads that may start
(:meth:`SceneLoader.next_job`, then :meth:`SceneLoader.run`) and finishes each on its own thread
(an EGL renderer is built there). What runs off the serving thread is
:func:`~visfly_dist.scene_worker.state.prepare_scene`. Measured per default garage on a 2-core
host: generating it takes 84 ms of CPU in pure Python (it holds the GIL: two threads generating
garages took 0.6-0.9x the time of one), its obstacle structures 59 ms (partly native) and its
raycast BVH 10 ms (native). So loads run beside each other only where generation runs in child
processes (:mod:`visfly_dist.scene_worker.generation`):

- **Before the first step** (start-up, a replacement taking over): up to ``parallel`` loads at
  once, ``parallel`` being the worker's thread share (``--threads``) capped at
  :data:`MAX_PARALLEL_LOADS`. Once :data:`CHILDREN_AFTER` generated loads wait at once (a start-up
  burst), ``parallel - 1`` child processes start: with the worker's own process (whose loader
  threads mostly take turns on the GIL) they fill its thread share. While they import, and for
  loads that are not generated, loads run one at a time as they always did. From when they are
  ready, a ``gen:`` source is generated in a child and its loader thread builds the rest from the
  scene it gets back. A worker with one thread never starts children.
- **Once steps are served** (swaps, rebalancing): one load at a time, in-thread, on a thread at
  :data:`BACKGROUND_LOAD_NICE`, so loads never take more from the steps than one niced thread; the
  children exit (each holds about 120 MB) when the first step is served.
- **Memory** (``--max-memory-mb``): a load starts beside others only while the worker's resident
  memory plus :data:`~visfly_dist.scene_worker.limits.LOAD_RESERVE_BYTES` per load running (this
  one included) stays within the bound; a load that would start alone only needs the worker under
  its bound, and each load is checked again once built, as a single load always was.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import deque
from concurrent.futures import CancelledError, Future, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

from visfly_dist.host import usable_cores
from visfly_dist.protocol.messages import LoadScene
from visfly_dist.scene_worker.generation import GeneratorProcesses, is_generated
from visfly_dist.scene_worker.state import PreparedScene, prepare_scene
from visfly_dist.scenes.scene import Scene

log = logging.getLogger(__name__)

Respond = Callable[[bool, bytes], None]
"""Sends one answer: ``(True, reply)`` or ``(False, error reply)``."""

MAX_PARALLEL_LOADS = 8
"""Most loads one worker runs at once, whatever its thread share."""
CHILDREN_AFTER = 8
"""Generated loads waiting at once that start the child processes. A child costs one to two seconds
of CPU to start and takes about 70 ms of the worker's own CPU per garage off it (160 -> 90 ms):
a burst pays, a single load not."""
BACKGROUND_LOAD_NICE = 10
"""Niceness of the thread that loads scenes once steps are served. Generating a scene takes a few
hundred ms of CPU (a garage: about 0.3 s on a loaded host); at the same priority, swaps during
training doubled the render time of every step on a 2-core machine."""


def parallel_loads(threads: int | None) -> int:
    """Loads a worker with ``threads`` tracing threads (``None``: this host's cores, at most 8) runs at once."""
    return max(1, min(MAX_PARALLEL_LOADS, threads or min(8, usable_cores())))


@dataclass(eq=False)
class LoadJob:
    """A ``load_scene`` accepted: who to answer, since when, and its heavy half once started.

    Attributes:
        background: it runs on the niced loader (it started once steps were served).
        child_s: seconds its scene took to come back from a child process (None: made in-thread).
    """

    request: LoadScene
    respond: Respond
    start: float
    future: Future[PreparedScene] | None = field(default=None, repr=False)
    background: bool = False
    child_s: float | None = None


class SceneLoader:
    """The waiting loads, the loader threads and the generator processes of one worker.

    Used from the serving thread only, except ``done(job)``, which the loader thread calls when a
    load's heavy half ends (the worker puts the job in its inbox there).

    Args:
        roots, backend, threads: as :func:`~visfly_dist.scene_worker.state.prepare_scene` takes them.
        parallel: most loads at once before the first step (:func:`parallel_loads`).
        reserve_bytes: memory set aside per load running when deciding whether another may start beside.
        done: called with a job once its ``future`` is done.
    """

    def __init__(self, roots: Sequence[Path], backend: str, threads: int | None, parallel: int, reserve_bytes: int,
                 done: Callable[[LoadJob], None]) -> None:
        self.roots = list(roots)
        self.backend = backend
        self.threads = threads
        self.parallel = parallel
        self.reserve_bytes = reserve_bytes
        self._done = done
        self._waiting: deque[LoadJob] = deque()
        self._running = {False: 0, True: 0}   # loads running, by background
        self._stepping = False
        self._children: GeneratorProcesses | None = None
        self._foreground = ThreadPoolExecutor(max_workers=parallel, thread_name_prefix="scene-loader")
        self._background = ThreadPoolExecutor(max_workers=1, thread_name_prefix="scene-loader-background",
                                              initializer=_lower_priority)

    def add(self, job: LoadJob) -> None:
        """Queue an accepted load; a burst of generated loads before the first step starts the children."""
        self._waiting.append(job)
        if (self._children is None and not self._stepping and self.parallel > 1
                and sum(is_generated(j.request.source) for j in self._waiting) >= CHILDREN_AFTER):
            log.info("%d generated loads wait: starting %d scene generator processes", len(self._waiting),
                     self.parallel - 1)
            self._children = GeneratorProcesses(self.parallel - 1)

    def next_job(self, used_bytes: int | None, bound_bytes: int) -> LoadJob | None:
        """The waiting load that may start now (taken off the queue), or None while it must wait.

        ``used_bytes`` is the worker's resident memory now (None: unknown, no memory gate).
        """
        if not self._waiting:
            return None
        limit = self.parallel if not self._stepping and self._children is not None and self._children.ready else 1
        if self._running[self._stepping] >= limit:
            return None
        busy = self._running[False] + self._running[True]
        if busy and used_bytes is not None and used_bytes + (busy + 1) * self.reserve_bytes > bound_bytes:
            return None
        return self._waiting.popleft()

    def run(self, job: LoadJob) -> None:
        """Start ``job``'s heavy half; ``done(job)`` follows on the loader thread."""
        job.background = self._stepping
        self._running[job.background] += 1
        child = None
        if (not job.background and self._children is not None and self._children.ready
                and is_generated(job.request.source)):
            try:
                child = self._children.submit(job.request.source, self.roots)
            except BrokenProcessPool:  # a child died (killed, out of memory): the next burst starts new ones
                log.warning("a scene generator process died; loads are generated in-thread until the next burst")
                self._children.close()
                self._children = None
        executor = self._background if job.background else self._foreground
        job.future = executor.submit(self._prepare, job, child)
        job.future.add_done_callback(lambda _: self._done(job))

    def _prepare(self, job: LoadJob, child: Future[Scene] | None) -> PreparedScene:
        """On a loader thread: the scene from ``child`` (or made here), then its queries and renderer."""
        scene = None
        if child is not None:
            start = time.perf_counter()
            try:
                scene = child.result()
            except (BrokenProcessPool, CancelledError) as exc:  # a child died or the worker closes: make it here
                log.warning("scene generator process lost (%s); generating %r in-thread", type(exc).__name__,
                            job.request.source)
            else:
                job.child_s = time.perf_counter() - start
        return prepare_scene(job.request, self.roots, self.backend, self.threads, scene)

    def finished(self, job: LoadJob) -> None:
        """``job``'s heavy half has ended (its result taken or dropped)."""
        self._running[job.background] -= 1

    def steps_began(self) -> None:
        """Steps are served from now on: later loads run one at a time, niced; the children exit."""
        self._stepping = True
        if self._children is not None:
            self._children.close()
            self._children = None

    def close(self) -> None:
        """Drop the waiting loads and stop the threads and children (loads running are not awaited)."""
        self._waiting.clear()
        self._foreground.shutdown(wait=False, cancel_futures=True)
        self._background.shutdown(wait=False, cancel_futures=True)
        if self._children is not None:
            self._children.close(cancel=True)
            self._children = None


def _lower_priority() -> None:
    """Run the calling thread at :data:`BACKGROUND_LOAD_NICE` or nicer (Linux threads have their own niceness)."""
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, max(BACKGROUND_LOAD_NICE, os.getpriority(os.PRIO_PROCESS, tid)))
    except (OSError, AttributeError):  # not Linux, or not allowed: loads keep the worker's priority
        log.info("could not lower the background loader's priority")
