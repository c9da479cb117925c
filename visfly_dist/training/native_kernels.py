"""The optional native kernels of the training path (``training/native/libvisfly_kernels.so``).

Built by ``setup.sh`` (``make -C visfly_dist/training/native``; needs g++). Without the library,
or with ``VISFLY_NATIVE_KERNELS=0``, callers use torch's own operations: same results, slower.
"""

from __future__ import annotations

import ctypes
import functools
from pathlib import Path

from visfly_dist.native import declare, load_native

LIBRARY_PATH = Path(__file__).parent / "native" / "libvisfly_kernels.so"
LIBRARY_VERSION = 1
DISABLE_ENV = "VISFLY_NATIVE_KERNELS"


@functools.lru_cache(maxsize=1)
def load_kernels() -> tuple[ctypes.CDLL | None, str]:
    """The loaded kernel library, or ``None`` and the reason it is not used."""
    return load_native(LIBRARY_PATH, "vf_kernels_version", LIBRARY_VERSION, DISABLE_ENV, "g++", _declare)


def _declare(lib: ctypes.CDLL) -> None:
    declare(lib, ("vf_phase_max_forward", "vf_phase_max_backward"), None,
            [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64])
