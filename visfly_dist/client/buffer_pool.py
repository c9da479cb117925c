"""Reusable CPU arrays for the large tensors the env hands out (merged images of a reset step).

A fresh 16 MB tensor costs the learner a page fault and a zeroed page per 4 KB: glibc serves
allocations that large with new pages from the kernel and hands them back on free. A buffer of
this pool keeps its pages.

Ownership (leases): each time a buffer is handed out, the tensor is made over a fresh array, the
*lease*, viewing the buffer's memory through a ``memoryview``; the pool keeps only a ``weakref`` to
it. Everything made from the tensor (a view of it, ``tensor.numpy()``, a slice of that) keeps its
storage, and with it the lease, alive; a numpy view of the lease has the lease as its ``.base``.
The buffer is free again once its lease is gone, so an observation a caller keeps is never written
over, however many references there are; no reference count is read. A lease kept alive longer
(in a reference cycle) only delays the reuse.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
import torch

POOL_SIZE = 4
"""Buffers kept: the observation a caller holds, the one being made, and slack for a few kept longer."""


@dataclass(eq=False)
class _Buffer:
    memory: np.ndarray  # owns the pages; never handed out
    lease: weakref.ref[np.ndarray] | None = None  # the array the last tensor handed out is made over

    def free(self) -> bool:
        return self.lease is None or self.lease() is None

    def lend(self, shape: tuple[int, ...]) -> torch.Tensor:
        lease = np.frombuffer(self.memory.data, self.memory.dtype)  # a memoryview: views of the lease keep it
        self.lease = weakref.ref(lease)
        return torch.from_numpy(lease.reshape(shape))


class BufferPool:
    """A bounded set of ``ndarray`` buffers handed out as torch tensors, reused once nobody holds them."""

    def __init__(self, size: int = POOL_SIZE) -> None:
        self._buffers: list[_Buffer] = []
        self._size = size
        self._next = 0  # the entry replaced when every buffer is held

    def take(self, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
        """An uninitialised CPU tensor of ``shape`` and ``dtype`` that nothing else refers to."""
        np_dtype = torch.empty((), dtype=dtype).numpy().dtype
        for buf in self._buffers:
            if buf.memory.shape == shape and buf.memory.dtype == np_dtype and buf.free():
                return buf.lend(shape)
        buf = _Buffer(np.empty(shape, np_dtype))
        if len(self._buffers) < self._size:
            self._buffers.append(buf)
        else:  # every buffer is held (or of another shape): keep the newest, the likeliest to come back
            self._buffers[self._next] = buf
            self._next = (self._next + 1) % self._size
        return buf.lend(shape)
