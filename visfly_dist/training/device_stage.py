"""A step's host tensors on the learner's GPU in one copy, through pinned memory.

A rollout step brings the learner its observation (the depth image and the vectors), rewards and
end flags as CPU tensors. Moved one by one from pageable memory, each is its own synchronous copy
(CUDA stages pageable memory through a pinned buffer of its own and returns when done). Here they
are packed into one pinned buffer (a memcpy each, 16-byte aligned) and cross in one asynchronous
copy; the device tensors are views of its result. Two pinned buffers take turns, each reused only
once its previous copy has finished (an event), so packing step ``t + 1`` never races the copy of
step ``t``.
"""

from __future__ import annotations

import torch

ALIGN = 16
"""Byte alignment of each tensor in the packed buffer (any element type can be viewed there)."""
SLOTS = 2


class DeviceStage:
    """``stage(tensors)``: the same tensors on ``device``, moved in one copy (identity on a CPU).

    Args:
        device: the learner's device.
    """

    def __init__(self, device: torch.device) -> None:
        self.device = torch.device(device)
        self._buffers: list[torch.Tensor | None] = [None] * SLOTS
        self._copied: list[torch.cuda.Event | None] = [None] * SLOTS
        self._turn = 0

    def __call__(self, tensors: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        if self.device.type != "cuda":
            return {k: v.detach().to(self.device) for k, v in tensors.items()}
        layout, total = packed_layout(tensors)
        slot = self._turn
        self._turn = (self._turn + 1) % SLOTS
        buffer = self._pinned(slot, total)
        pack(tensors, layout, buffer)
        moved = buffer[:total].to(self.device, non_blocking=True)
        event = torch.cuda.Event()
        event.record()
        self._copied[slot] = event
        return unpack(moved, layout)

    def _pinned(self, slot: int, nbytes: int) -> torch.Tensor:
        """Slot ``slot``'s pinned buffer, at least ``nbytes`` long, once its last copy is done."""
        event = self._copied[slot]
        if event is not None:
            event.synchronize()
        buffer = self._buffers[slot]
        if buffer is None or buffer.numel() < nbytes:
            buffer = torch.empty(max(nbytes, 1), dtype=torch.uint8, pin_memory=True)
            self._buffers[slot] = buffer
        return buffer


Layout = list[tuple[str, torch.dtype, torch.Size, int]]


def packed_layout(tensors: dict[str, torch.Tensor]) -> tuple[Layout, int]:
    """Each tensor's name, dtype, shape and byte offset in the packed buffer, and its length."""
    layout, total = [], 0
    for name, tensor in tensors.items():
        layout.append((name, tensor.dtype, tensor.shape, total))
        total += -(-tensor.numel() * tensor.element_size() // ALIGN) * ALIGN
    return layout, total


def pack(tensors: dict[str, torch.Tensor], layout: Layout, buffer: torch.Tensor) -> None:
    """Copy ``tensors`` into the uint8 ``buffer`` at their offsets."""
    for name, _, _, offset in layout:
        raw = tensors[name].detach().contiguous().view(-1).view(torch.uint8)
        buffer[offset:offset + raw.numel()].copy_(raw)


def unpack(buffer: torch.Tensor, layout: Layout) -> dict[str, torch.Tensor]:
    """The tensors of ``layout`` as views of the uint8 ``buffer``."""
    out = {}
    for name, dtype, shape, offset in layout:
        out[name] = buffer[offset:offset + shape.numel() * dtype.itemsize].view(dtype).view(shape)
    return out
