"""Reusable CPU arrays for the large tensors the env hands out (merged images of a reset step).

A fresh 16 MB tensor costs the learner a page fault and a zeroed page per 4 KB: glibc serves
allocations that large with new pages from the kernel and hands them back on free. A buffer of
this pool keeps its pages. ``torch.from_numpy`` keeps a reference to its ``ndarray`` for as long
as any tensor over it (or a numpy view of such a tensor) is alive, so the array's reference count
says whether anyone still holds what was handed out: a buffer is offered again only when nobody
does, and an observation a caller keeps is never written over.
"""

from __future__ import annotations

import sys

import numpy as np
import torch

POOL_SIZE = 4
"""Buffers kept: the observation a caller holds, the one being made, and slack for a few kept longer."""


class BufferPool:
    """A bounded set of ``ndarray`` buffers handed out as torch tensors, reused once nobody holds them."""

    def __init__(self, size: int = POOL_SIZE) -> None:
        self._arrays: list[np.ndarray] = []
        self._size = size
        self._next = 0  # the entry replaced when every buffer is held
        self._baseline = _unheld_refcount()

    def take(self, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
        """An uninitialised CPU tensor of ``shape`` and ``dtype`` that nothing else refers to."""
        np_dtype = torch.empty((), dtype=dtype).numpy().dtype
        for array in self._arrays:
            if array.shape == shape and array.dtype == np_dtype and sys.getrefcount(array) <= self._baseline:
                return torch.from_numpy(array)
        array = np.empty(shape, np_dtype)
        if len(self._arrays) < self._size:
            self._arrays.append(array)
        else:  # every buffer is held (or of another shape): keep the newest, the likeliest to come back
            self._arrays[self._next] = array
            self._next = (self._next + 1) % self._size
        return torch.from_numpy(array)


def _unheld_refcount() -> int:
    """``sys.getrefcount`` of an array that only a list entry and a local name refer to (as in ``take``'s loop)."""
    arrays = [np.empty(1)]
    array = arrays[0]
    return sys.getrefcount(array)
