"""The optional native kernels of the training path (``training/native/libvisfly_kernels.so``).

Built by ``setup.sh`` (``make -C visfly_dist/training/native``; needs g++). Without the library,
or with ``VISFLY_NATIVE_KERNELS=0``, callers use torch's own operations: same results, slower.
"""

from __future__ import annotations

import ctypes
import functools
import os
from pathlib import Path

LIBRARY_PATH = Path(__file__).parent / "native" / "libvisfly_kernels.so"
LIBRARY_VERSION = 1
DISABLE_ENV = "VISFLY_NATIVE_KERNELS"


@functools.lru_cache(maxsize=1)
def load_kernels() -> tuple[ctypes.CDLL | None, str]:
    """The loaded kernel library, or ``None`` and the reason it is not used."""
    if os.environ.get(DISABLE_ENV, "1") == "0":
        return None, f"disabled by {DISABLE_ENV}=0"
    if not LIBRARY_PATH.exists():
        return None, f"{LIBRARY_PATH} not built (make -C {LIBRARY_PATH.parent}; needs g++)"
    try:
        lib = ctypes.CDLL(str(LIBRARY_PATH))
        lib.vf_kernels_version.restype = ctypes.c_int
        if lib.vf_kernels_version() != LIBRARY_VERSION:
            return None, f"{LIBRARY_PATH} is version {lib.vf_kernels_version()}, expected {LIBRARY_VERSION}; rebuild it"
        for name in ("vf_phase_max_forward", "vf_phase_max_backward"):
            fn = getattr(lib, name)
            fn.restype = None
            fn.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64]
    except (OSError, AttributeError) as exc:
        return None, f"{LIBRARY_PATH} failed to load: {exc}"
    return lib, "loaded"
