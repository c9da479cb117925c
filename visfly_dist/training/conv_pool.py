"""A convolution followed by a 2x2 max-pool, computed as one convolution over space-to-depth input.

``max_pool2d(conv2d(x, w, b), 2)`` evaluates the convolution at every pixel and then keeps one of
each 2x2 block. Here the input is first rearranged so that each 2x2 block becomes 4 channels
(``pixel_unshuffle``); the convolution's four output phases (which pixel of the block) then become
one convolution with 4x the output channels over a quarter of the positions, and the pool is a
maximum over the four phases. Same function, same parameters, different arithmetic order
(results agree to float32 rounding).

Why: a convolution over 1-3 input channels (the first layer of an image trunk) leaves CPU
convolution kernels far from their best, and the pool over its large output costs as much again.
Measured on a 2-core AMD EPYC with torch 2.13, one thread, batch 512, VisFly's first layer (6
channels, kernel 5), channels-last: forward and backward 1.3x faster on 64x64 depth (124 against
163 ms) and on 64x64 RGB (240 against 320 ms), forward without gradients (rollout inference) 2x
faster on depth. With 6 or more input channels the phase form does more arithmetic (1.8x for
kernel 3) and is slower, so :func:`conv_maxpool2` uses it only up to ``PHASE_MAX_IN_CHANNELS``.
Gradients at tied maxima go to one of the tied phases, as ``max_pool2d``'s do.

The phase form also needs even input sizes and an even convolution output (64x64 input and a
kernel of 5 qualify); :func:`conv_maxpool2` falls back to the plain form otherwise.
"""

from __future__ import annotations

import weakref
from typing import Any

import torch
import torch.nn.functional as F

from visfly_dist.training.native_kernels import load_kernels

PHASE_MAX_IN_CHANNELS = 3
"""Above this many input channels the plain convolution and pool are faster."""

_PhaseParams = tuple[tuple[int, ...], torch.Tensor, "torch.Tensor | None"]
_PHASE_PARAMS: "weakref.WeakKeyDictionary[torch.nn.Conv2d, _PhaseParams]" = weakref.WeakKeyDictionary()
"""Per convolution: the phase kernel and bias of its parameters at a version (see :func:`phase_params`)."""


def phase_weight(weight: torch.Tensor) -> torch.Tensor:
    """``(O, C, k, k)`` kernel -> ``(4 O, 4 C, K, K)`` kernel over space-to-depth input, ``K = (k + 2) // 2``.

    Output channel ``4 o + 2 a + b`` is phase ``(a, b)`` of channel ``o``; input channel ``4 c + 2 p + q``
    is ``x[c, 2 m + p, 2 n + q]`` (``pixel_unshuffle``'s order). Entry ``[o, a, b, c, p, q, m, n]`` is
    ``w[o, c, 2 m + p - a, 2 n + q - b]``, zero where that index falls outside the kernel.
    """
    out_ch, in_ch, k, k2 = weight.shape
    if k != k2:
        raise ValueError(f"phase_weight needs a square kernel, got {k}x{k2}")
    size = (k + 2) // 2
    padded = F.pad(weight, (1, 2 * size - k, 1, 2 * size - k))  # index u + 1 for u in [-1, 2 size - 1]
    m = torch.arange(size, device=weight.device)  # on the weight's device: no host tensor mixed in
    two = torch.arange(2, device=weight.device)
    # idx[a, p, m] = 2 m + p - a + 1
    idx = 2 * m[None, None, :] + two[None, :, None] - two[:, None, None] + 1
    rows = idx[:, None, :, None, :, None].expand(2, 2, 2, 2, size, size)  # (a, b, p, q, m, n) -> u index
    cols = idx[None, :, None, :, None, :].expand(2, 2, 2, 2, size, size)  # (a, b, p, q, m, n) -> v index
    gathered = padded[:, :, rows, cols]  # (O, C, a, b, p, q, m, n)
    return gathered.permute(0, 2, 3, 1, 4, 5, 6, 7).reshape(out_ch * 4, in_ch * 4, size, size)


def phase_form_applies(height: int, width: int, kernel: int) -> bool:
    """Whether the phase form computes ``max_pool2d(conv2d(x), 2)`` exactly for this input size."""
    return all(n % 2 == 0 and (n - kernel + 1) % 2 == 0 and n - kernel + 1 >= 2 for n in (height, width))


def conv_maxpool2(x: torch.Tensor, conv: torch.nn.Conv2d) -> torch.Tensor:
    """``max_pool2d(conv(x), 2)`` for a stride-1, unpadded, undilated, ungrouped ``conv``.

    Uses the phase form (returning a channels-last tensor) on a CPU, for at most
    ``PHASE_MAX_IN_CHANNELS`` input channels when :func:`phase_form_applies`; else the plain
    convolution and pool. On a GPU the plain pair is cuDNN's and the phase form only adds
    operations, each a kernel launch: counted on the policy of the navigation task, a minibatch's
    forward and backward pass is 338 operations in the phase form against 268 plain, a forward pass
    without gradients 128 against 72.
    """
    kernel, other = conv.kernel_size
    simple = conv.stride == (1, 1) and conv.padding == (0, 0) and conv.dilation == (1, 1) and conv.groups == 1
    if (not x.is_cpu or conv.in_channels > PHASE_MAX_IN_CHANNELS or not simple or kernel != other
            or not phase_form_applies(x.shape[2], x.shape[3], kernel)):
        return F.max_pool2d(conv(x), 2)
    batch, out_ch = x.shape[0], conv.out_channels
    unshuffled = space_to_depth(x)
    weight, bias = phase_params(conv)
    phases = F.conv2d(unshuffled, weight, bias)  # (B, 4 O, H', W'), channels-last
    height, width = phases.shape[2], phases.shape[3]
    grouped = phases.permute(0, 2, 3, 1).reshape(batch, height, width, out_ch, 4)
    return phase_max(grouped).permute(0, 3, 1, 2)


def _records_grad(*tensors: torch.Tensor) -> bool:
    """Whether autograd records an operation on ``tensors`` here (grad mode on, one of them needs it)."""
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)


def space_to_depth(x: torch.Tensor) -> torch.Tensor:
    """``pixel_unshuffle(x, 2)`` in channels-last memory.

    Without gradients it is written as four strided copies, one per phase (2x faster than
    ``pixel_unshuffle`` and the layout change at 16 images, 3-7x at 512); with gradients torch's
    own pair, whose backward pass is the faster one.
    """
    if _records_grad(x):
        return F.pixel_unshuffle(x, 2).contiguous(memory_format=torch.channels_last)
    batch, channels, height, width = x.shape
    out = torch.empty(batch, height // 2, width // 2, channels, 4, dtype=x.dtype, device=x.device)
    for p in range(2):
        for q in range(2):
            out[..., 2 * p + q].copy_(x[:, :, p::2, q::2].permute(0, 2, 3, 1))
    return out.reshape(batch, height // 2, width // 2, 4 * channels).permute(0, 3, 1, 2)


def phase_params(conv: torch.nn.Conv2d) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The phase kernel (:func:`phase_weight`) and the bias (each repeated 4 times) of ``conv``.

    With gradients they are recomputed, so that autograd reaches ``conv``'s parameters. Without
    (rollout inference) they are kept per convolution and rebuilt only when a parameter changed:
    the key is each parameter's identity, storage and in-place version counter, which optimizer
    steps and ``load_state_dict`` advance. That saves two small kernels per forward pass. (Only a
    CPU runs the phase form: nothing here is captured in a CUDA graph, whose replay would keep
    the kernel of its capture.)
    """
    params = [p for p in (conv.weight, conv.bias) if p is not None]
    if _records_grad(*params):
        return phase_weight(conv.weight), None if conv.bias is None else conv.bias.repeat_interleave(4)
    key = tuple(v for p in params for v in (id(p), p.data_ptr(), p._version))
    cached = _PHASE_PARAMS.get(conv)
    if cached is None or cached[0] != key:
        with torch.no_grad():
            bias = None if conv.bias is None else conv.bias.repeat_interleave(4)
            cached = (key, phase_weight(conv.weight), bias)
        _PHASE_PARAMS[conv] = cached
    return cached[1], cached[2]


def phase_max(grouped: torch.Tensor) -> torch.Tensor:
    """Maximum over the last axis (size 4); the gradient goes to the first maximal entry.

    Uses the native kernel (:mod:`~visfly_dist.training.native_kernels`) for float32 CPU tensors
    (without gradients too: 2x faster than ``amax`` on a rollout's 16 images); without it,
    ``amax`` when no gradient is needed, else torch's ``max`` with indices.
    """
    lib, _ = load_kernels()
    native = lib is not None and grouped.dtype == torch.float32 and grouped.device.type == "cpu"
    if not _records_grad(grouped):
        return _native_phase_max(lib, grouped)[0] if native else grouped.amax(-1)
    return _NativePhaseMax.apply(grouped) if native else grouped.max(-1).values


def _native_phase_max(lib: Any, grouped: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The maximum over the last axis and the uint8 index of the first maximal entry (native)."""
    grouped = grouped.detach().contiguous()
    out = torch.empty(grouped.shape[:-1], dtype=grouped.dtype)
    index = torch.empty(grouped.shape[:-1], dtype=torch.uint8)
    lib.vf_phase_max_forward(grouped.data_ptr(), out.data_ptr(), index.data_ptr(), out.numel())
    return out, index


class _NativePhaseMax(torch.autograd.Function):
    """``max(-1)`` over 4 phases with a uint8 index, in the native kernel (no int64 indices)."""

    @staticmethod
    def forward(ctx: Any, grouped: torch.Tensor) -> torch.Tensor:
        lib, _ = load_kernels()
        out, index = _native_phase_max(lib, grouped)
        ctx.save_for_backward(index)
        return out

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> torch.Tensor:
        lib, _ = load_kernels()
        assert lib is not None, "forward ran the native kernel"
        (index,) = ctx.saved_tensors
        grad = grad.contiguous().to(torch.float32)
        grad_in = torch.empty((*index.shape, 4), dtype=torch.float32)
        lib.vf_phase_max_backward(grad.data_ptr(), index.data_ptr(), grad_in.data_ptr(), index.numel())
        return grad_in
