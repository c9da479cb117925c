"""Child processes that generate ``gen:`` scenes for a worker's loads.

Generating a scene is pure Python and numpy on small arrays: it holds the GIL, so two loader
threads cannot generate two scenes at once. A child process can: it resolves the source and sends
the :class:`~visfly_dist.scenes.scene.Scene` back pickled (about 1 MB and 12 ms to unpickle for a
default garage); the worker's loader thread then builds the obstacle queries and renderer from it.

The children are spawned, not forked (the worker holds Zenoh's threads, and maybe GL contexts),
and this module stays light: a child imports only it and :mod:`visfly_dist.scenes`. A child
ignores SIGINT (a terminal's Ctrl-C stops the worker, which stops its children) and exits by itself
within :data:`PARENT_POLL_S` once the worker is gone, even after a SIGKILL.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import threading
import time
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path
from typing import Sequence

from visfly_dist.scenes.scene import Scene
from visfly_dist.scenes.source_syntax import GEN_PREFIX
from visfly_dist.scenes.sources import resolve_source

log = logging.getLogger(__name__)

PARENT_POLL_S = 0.5
"""How often a child checks that the worker that spawned it is still its parent."""


def is_generated(source: str) -> bool:
    """Whether ``source`` is a generator spec (``gen:...``), the kind of source a child generates."""
    return source.startswith(GEN_PREFIX)


class GeneratorProcesses:
    """``processes`` spawned children that generate scenes; they start importing at once.

    Use :attr:`ready` before :meth:`submit`: until every child has imported the scene generators
    (about a second of CPU each), a load is better generated in-thread than queued behind imports.
    """

    def __init__(self, processes: int) -> None:
        self.processes = processes
        self._pool = ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_child_start, initargs=(os.getpid(),))
        # One task per child: the pool spawns a process per task while none is idle.
        self._warm = [self._pool.submit(os.getpid) for _ in range(processes)]
        self._failure_logged = False

    @property
    def ready(self) -> bool:
        """Every child has started and imported the generators (False for good if one failed)."""
        if not all(f.done() for f in self._warm):
            return False
        failed = next((f.exception() for f in self._warm if f.exception() is not None), None)
        if failed is not None and not self._failure_logged:
            self._failure_logged = True
            log.warning("scene generator processes failed to start (%s); loads are generated in-thread", failed)
        return failed is None

    def submit(self, source: str, roots: Sequence[Path]) -> Future[Scene]:
        """Generate ``source`` (under ``roots``, for the confinement check) in a child."""
        return self._pool.submit(resolve_source, source, list(roots))

    def close(self, cancel: bool = False) -> None:
        """Let the children finish what was submitted (or, with ``cancel``, what they started) and exit."""
        self._pool.shutdown(wait=False, cancel_futures=cancel)


def _child_start(parent_pid: int) -> None:
    """In a child: ignore SIGINT and exit when ``parent_pid`` stops being the parent."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_POLL_S)
        os._exit(0)

    threading.Thread(target=watch, name="watch-parent", daemon=True).start()
