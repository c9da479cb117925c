"""Loading the optional native libraries (the tracer, the dynamics step, the training kernels).

Each is built by ``setup.sh`` with ``make -C <its folder>`` and is optional: when it is missing, of
another version or switched off by its environment variable, callers take their Python path and
say why once (the reason string). One loader keeps those rules the same for all of them.
"""

from __future__ import annotations

import ctypes
import os
from pathlib import Path
from typing import Any, Callable, Sequence


def load_native(path: Path, version_symbol: str, version: int, disable_env: str, needs: str,
                declare: Callable[[ctypes.CDLL], None]) -> tuple[ctypes.CDLL | None, str]:
    """The library at ``path``, or ``None`` and the reason it is not used.

    Args:
        path: the built ``.so``.
        version_symbol: its ``int (void)`` function returning the version it was built as.
        version: the version this Python code expects.
        disable_env: the environment variable that, set to ``0``, turns it off.
        needs: what building it needs (for the message when it is not built).
        declare: sets the ``restype``/``argtypes`` of the functions callers use.
    """
    if os.environ.get(disable_env, "1") == "0":
        return None, f"disabled by {disable_env}=0"
    if not path.exists():
        return None, f"{path} not built (make -C {path.parent}; needs {needs})"
    try:
        lib = ctypes.CDLL(str(path))
        get_version = getattr(lib, version_symbol)
        get_version.restype = ctypes.c_int
        found = get_version()
        if found != version:
            return None, f"{path} is version {found}, expected {version}; rebuild it"
        declare(lib)
    except (OSError, AttributeError) as exc:
        return None, f"{path} failed to load: {exc}"
    return lib, "loaded"


def declare(lib: ctypes.CDLL, names: Sequence[str], restype: Any, argtypes: list[Any]) -> None:
    """Give the functions ``names`` of ``lib`` one signature."""
    for name in names:
        fn = getattr(lib, name)
        fn.restype = restype
        fn.argtypes = argtypes
