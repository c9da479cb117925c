"""Zenoh shared-memory files (``/dev/shm/<number>.zenoh``) a process leaves behind.

Measured with eclipse-zenoh 1.10.2: a session keeps its segment files open (and flock'ed) until
the process exits, even after ``close()``, and a cleanly exiting process sometimes leaves them on
disk; a killed one always does. Zenoh removes files that no process holds open when the next
session on the host opens. :func:`remove_own_segments` applies that same rule to the files this
process holds, so a process that closed its sessions leaves nothing behind even when no other
Zenoh process ever runs on the host again.

Both sides use it: :func:`~visfly_dist.protocol.session.open_session` registers every session
with :func:`track`, and :func:`release_segments` (at interpreter exit, and by the worker command as
it stops) unlinks this process's files once every tracked session is closed. Unlinking while a
session of this process is still open would hide its pool from peers that have not mapped it yet,
hence the tracking.

Never call it while the process may still open a session: Zenoh keeps the buffer-header and
watchdog segments per process (global to it, not per session) and reuses them in every later
session. Once unlinked, a peer that first maps them afterwards (the worker of the next env made in
the same process) cannot resolve any shared-memory buffer this process sends; Zenoh drops such a
request silently and the sender gets ``Timeout``. Measured with 1.10.2 (the regression test
``tests/aggregator/test_sequential_pools.py``): the second of two pools made one after another got
no answer to its 5.6 kB step requests after the first pool's ``close()`` had released the files.
"""

from __future__ import annotations

import atexit
import os
import threading
from pathlib import Path
from typing import Any, Callable

SHM_DIR = Path("/dev/shm")

_lock = threading.Lock()
_sessions: list[Any] = []   # zenoh.Session objects cannot be weakly referenced; closed ones are pruned


def track(session: Any) -> Any:
    """Remember a Zenoh session of this process (for :func:`release_segments`); returns it."""
    with _lock:
        _sessions[:] = [s for s in _sessions if not s.is_closed()]
        _sessions.append(session)
    return session


def open_sessions() -> int:
    """How many tracked sessions of this process are still open."""
    with _lock:
        _sessions[:] = [s for s in _sessions if not s.is_closed()]
        return len(_sessions)


def release_segments() -> list[str]:
    """Unlink this process's Zenoh shared-memory files if every tracked session is closed.

    Call it only when this process opens no further session (it runs at interpreter exit; the
    worker command calls it as it stops): later sessions reuse Zenoh's per-process segments, which
    new peers could no longer map (see the module docstring). It does nothing while a session of
    this process is open. Mappings stay valid after an unlink, so nothing already mapped is disturbed.

    Returns:
        The removed paths (empty while a session is open).
    """
    if open_sessions():
        return []
    return remove_own_segments()


def _open_files_in(fd_dir: Path, wanted: Callable[[str], bool]) -> set[str]:
    """Paths among the open descriptors listed in ``fd_dir`` for which ``wanted(path)`` holds."""
    found: set[str] = set()
    try:
        entries = list(fd_dir.iterdir())
    except OSError:  # the process is gone, or not ours to inspect
        return found
    for fd in entries:
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if wanted(target):
            found.add(target)
    return found


def _is_zenoh_file(path: str) -> bool:
    return path.startswith(f"{SHM_DIR}/") and path.endswith(".zenoh")


def _zenoh_files_open_in(fd_dir: Path) -> set[str]:
    """Paths of ``/dev/shm/*.zenoh`` files among the open descriptors listed in ``fd_dir``."""
    return _open_files_in(fd_dir, _is_zenoh_file)


def _zenoh_files_open_elsewhere() -> set[str]:
    me = str(os.getpid())
    held: set[str] = set()
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit() and proc.name != me:
            held |= _zenoh_files_open_in(proc / "fd")
    return held


def orphaned_segments() -> set[str]:
    """Zenoh shared-memory files that no process (this one included) holds open."""
    if not SHM_DIR.is_dir():
        return set()
    on_disk = {str(p) for p in SHM_DIR.glob("*.zenoh")}
    return on_disk - _zenoh_files_open_elsewhere() - _zenoh_files_open_in(Path("/proc/self/fd"))


def remove_own_segments() -> list[str]:
    """Unlink the Zenoh shared-memory files this process holds open and no other process does.

    Call it only after every Zenoh session of this process is closed, just before exiting: the
    files are then nobody's but this process's, which is Zenoh's own rule for removing them.
    Mappings stay valid after an unlink, so a peer still reading a buffer is unaffected.

    Returns:
        The removed paths.
    """
    mine = _zenoh_files_open_in(Path("/proc/self/fd"))
    if not mine:
        return []
    removed = []
    for path in sorted(mine - _zenoh_files_open_elsewhere()):
        try:
            os.unlink(path)
        except FileNotFoundError:
            continue
        removed.append(path)
    return removed


atexit.register(release_segments)
