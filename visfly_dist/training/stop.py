"""A stop asked by a signal (Ctrl-C, SIGTERM): raised where it lands, and remembered until a trainer acts.

``visfly-dist train`` turns SIGINT and SIGTERM into ``KeyboardInterrupt``, as Python does for Ctrl-C,
so that the trainer saves its model and closes its workers. A library can swallow that exception
where it lands: trimesh's optional imports catch ``BaseException``, and a Ctrl-C in the first second
of a run (while the scene checks import it) vanished there, the run then training to its end. So
the stop is also remembered: trainers call :func:`raise_if_asked` once the env is up and after each
rollout, and :func:`taken` once they stopped.
"""

from __future__ import annotations

_asked: list[int] = []


def ask(signum: int) -> None:
    """A signal handler's body: remember the stop, then raise it here."""
    _asked.append(signum)
    raise KeyboardInterrupt(f"signal {signum}")


def raise_if_asked() -> None:
    """Raise ``KeyboardInterrupt`` for a stop that was asked and swallowed on its way."""
    if _asked:
        signum = _asked[0]
        _asked.clear()
        raise KeyboardInterrupt(f"signal {signum} (asked earlier)")


def taken() -> None:
    """The trainer stopped: forget the stop (a next run in this process starts afresh)."""
    _asked.clear()
