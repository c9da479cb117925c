"""The optional native kernels of the training path (``training/native/libvisfly_kernels.so``).

Built by ``setup.sh`` (``make -C visfly_dist/training/native``; needs g++): the image trunk's
pooling (:mod:`visfly_dist.training.conv_pool`) and the tensor PPO's normalisation of a step
(:class:`~visfly_dist.training.tensor_ppo.Normalizer`). Without the library, or with
``VISFLY_NATIVE_KERNELS=0``, callers use torch's own operations: same results, slower.
"""

from __future__ import annotations

import ctypes
import functools
from pathlib import Path
from typing import Sequence

import torch

from visfly_dist.native import declare, load_native

LIBRARY_PATH = Path(__file__).parent / "native" / "libvisfly_kernels.so"
LIBRARY_VERSION = 2
DISABLE_ENV = "VISFLY_NATIVE_KERNELS"


@functools.lru_cache(maxsize=1)
def load_kernels() -> tuple[ctypes.CDLL | None, str]:
    """The loaded kernel library, or ``None`` and the reason it is not used."""
    return load_native(LIBRARY_PATH, "vf_kernels_version", LIBRARY_VERSION, DISABLE_ENV, "g++", _declare)


def _declare(lib: ctypes.CDLL) -> None:
    pointer, count, real = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double
    declare(lib, ("vf_phase_max_forward", "vf_phase_max_backward"), None, [pointer, pointer, pointer, count])
    declare(lib, ("vf_normalize_obs_f32",), None,
            [pointer, pointer, pointer, count, count, pointer, pointer, pointer, pointer, real, real, real])
    declare(lib, ("vf_normalize_reward_f32",), None,
            [pointer, pointer, pointer, pointer, count, real, pointer, pointer, pointer, pointer, real, real,
             ctypes.c_float, pointer])


def addresses(tensors: Sequence[torch.Tensor]) -> ctypes.Array:
    """The data pointers of ``tensors``, a C array of them (a kernel's array argument)."""
    return (ctypes.c_void_p * len(tensors))(*[t.data_ptr() for t in tensors])
