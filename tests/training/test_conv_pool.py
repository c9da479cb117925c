"""The phase form of conv + 2x2 max-pool is the same function, with the same gradients, as the plain one."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from gymnasium import spaces
from torch import nn
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten

from visfly_dist.training.conv_pool import conv_maxpool2, phase_form_applies, phase_max, phase_weight, space_to_depth
from visfly_dist.training.native_kernels import load_kernels
from visfly_dist.training.extractors import VisflyExtractor


def _plain(x: torch.Tensor, conv: nn.Conv2d) -> torch.Tensor:
    return F.max_pool2d(conv(x), 2)


@pytest.mark.parametrize("in_ch,out_ch,kernel,size", [(1, 6, 5, 64), (3, 6, 5, 32), (1, 4, 3, 16), (2, 3, 4, 11), (6, 12, 3, 30)])
def test_values_and_gradients_match_the_plain_form(in_ch: int, out_ch: int, kernel: int, size: int) -> None:
    torch.manual_seed(0)
    conv = nn.Conv2d(in_ch, out_ch, kernel).double()
    x = torch.randn(3, in_ch, size, size, dtype=torch.float64, requires_grad=True)
    upstream = torch.randn_like(_plain(x, conv))
    grads = []
    for fn in (_plain, conv_maxpool2):
        conv.zero_grad()
        x.grad = None
        out = fn(x, conv)
        (out * upstream).sum().backward()
        grads.append((out.detach(), x.grad.clone(), conv.weight.grad.clone(), conv.bias.grad.clone()))
    for plain, phase in zip(*grads):
        torch.testing.assert_close(phase, plain, rtol=1e-10, atol=1e-10)


def test_the_phase_kernel_places_each_tap_once() -> None:
    """Every tap of the original kernel appears exactly once per output phase, and nothing else."""
    weight = torch.arange(1.0, 1 + 2 * 1 * 5 * 5).reshape(2, 1, 5, 5)
    phased = phase_weight(weight)  # (8, 4, 3, 3)
    assert phased.shape == (8, 4, 3, 3)
    for o in range(2):
        for phase in range(4):
            taps = phased[4 * o + phase].flatten()
            assert sorted(taps[taps != 0].tolist()) == sorted(weight[o].flatten().tolist())


def test_odd_sizes_use_the_plain_form() -> None:
    assert phase_form_applies(64, 64, 5) and phase_form_applies(30, 30, 3)
    assert not phase_form_applies(63, 64, 5)  # odd input
    assert not phase_form_applies(64, 64, 4)  # odd convolution output (61)


def test_tied_maxima_pass_the_gradient_once() -> None:
    """A constant image ties all four phases; the pooled gradient must not be counted four times."""
    conv = nn.Conv2d(1, 2, 3).double()
    x = torch.full((1, 1, 8, 8), 0.5, dtype=torch.float64, requires_grad=True)
    conv_maxpool2(x, conv).sum().backward()
    phase_grad = x.grad.clone()
    x.grad = None
    _plain(x, conv).sum().backward()
    assert phase_grad.sum().item() == pytest.approx(x.grad.sum().item())


def test_extractor_parameters_are_named_as_before() -> None:
    """Checkpoints of the plain trunk load into the fused one and give the same features."""
    space = spaces.Dict({"depth": spaces.Box(0, 20, (1, 64, 64), np.float32)})
    torch.manual_seed(1)
    fused = VisflyExtractor(space)
    plain_trunk = nn.Sequential(*fused.encoders["depth"].trunk)
    assert list(plain_trunk.state_dict()) == list(fused.encoders["depth"].trunk.state_dict())
    x = {"depth": torch.rand(4, 1, 64, 64) * 20}
    with torch.no_grad():
        normalised = fused.encoders["depth"].normalizer(x["depth"])
        torch.testing.assert_close(fused.encoders["depth"].trunk(normalised), plain_trunk(normalised), rtol=1e-5, atol=1e-5)


needs_kernels = pytest.mark.skipif(load_kernels()[0] is None, reason=f"native kernels: {load_kernels()[1]}")


@needs_kernels
def test_native_phase_max_matches_torch_max() -> None:
    torch.manual_seed(2)
    grouped = torch.randn(5, 7, 3, 6, 4, requires_grad=True)
    upstream = torch.randn(5, 7, 3, 6)
    native = phase_max(grouped)
    (native * upstream).sum().backward()
    native_grad = grouped.grad.clone()
    grouped.grad = None
    reference = grouped.max(-1).values
    (reference * upstream).sum().backward()
    assert torch.equal(native, reference) and torch.equal(native_grad, grouped.grad)


@needs_kernels
def test_native_phase_max_ties_go_to_the_first_and_nan_wins() -> None:
    grouped = torch.tensor([[1.0, 3.0, 3.0, 2.0], [0.5, float("nan"), 9.0, 1.0], [4.0, 4.0, 4.0, 4.0]], requires_grad=True)
    out = phase_max(grouped)
    assert out[0].item() == 3.0 and torch.isnan(out[1]) and out[2].item() == 4.0
    out.backward(torch.ones_like(out))
    assert grouped.grad.tolist() == [[0.0, 1.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]]


@needs_kernels
def test_native_phase_max_without_grad_equals_amax() -> None:
    torch.manual_seed(3)
    grouped = torch.randn(16, 30, 30, 6, 4)
    with torch.no_grad():
        assert torch.equal(phase_max(grouped), grouped.amax(-1))
    assert torch.equal(phase_max(grouped), grouped.amax(-1))  # a tensor that needs no gradient


def test_inference_keeps_the_phase_kernel_until_a_parameter_changes() -> None:
    """Without gradients the phase kernel is reused; an optimizer step or a loaded state rebuilds it."""
    torch.manual_seed(4)
    conv = nn.Conv2d(1, 6, 5)
    x = torch.rand(4, 1, 64, 64)
    with torch.no_grad():
        first = conv_maxpool2(x, conv)
        assert torch.equal(conv_maxpool2(x, conv), first)
        torch.testing.assert_close(first, _plain(x, conv), rtol=1e-5, atol=1e-5)
    optimizer = torch.optim.SGD(conv.parameters(), lr=0.5)
    conv_maxpool2(x, conv).sum().backward()  # with gradients: built fresh, reaches the parameters
    assert conv.weight.grad is not None and conv.bias.grad is not None
    optimizer.step()
    with torch.no_grad():
        stepped = conv_maxpool2(x, conv)
        assert not torch.equal(stepped, first)
        assert torch.equal(stepped, conv_maxpool2(x, conv.requires_grad_(False)))
        torch.testing.assert_close(stepped, _plain(x, conv), rtol=1e-5, atol=1e-5)
        conv.load_state_dict({"weight": torch.zeros_like(conv.weight), "bias": torch.ones_like(conv.bias)})
        assert torch.equal(conv_maxpool2(x, conv), torch.ones_like(first))


@pytest.mark.parametrize("channels", [1, 3])
def test_space_to_depth_without_grad_is_pixel_unshuffle_channels_last(channels: int) -> None:
    x = torch.rand(5, channels, 12, 8).contiguous(memory_format=torch.channels_last)
    reference = F.pixel_unshuffle(x, 2).contiguous(memory_format=torch.channels_last)
    with torch.no_grad():
        out = space_to_depth(x)
    assert torch.equal(out, reference) and out.stride() == reference.stride()


def test_the_phase_kernel_is_built_on_its_weights_device() -> None:
    """No operation of :func:`phase_weight` takes a tensor from another device than the weight's
    (index tensors made on the CPU made CUDA graph captures fail when a GPU ran the phase form)."""
    class DevicesPerOp(TorchDispatchMode):
        def __init__(self) -> None:
            super().__init__()
            self.mixed: list[str] = []

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # type: ignore[no-untyped-def]
            flat, _ = tree_flatten((args, kwargs or {}))
            if {t.device.type for t in flat if isinstance(t, torch.Tensor)} - {"meta"}:
                self.mixed.append(str(func))
            return func(*args, **(kwargs or {}))

    weight = torch.empty(6, 1, 5, 5, device="meta")
    with DevicesPerOp() as mode:
        phased = phase_weight(weight)
    assert phased.device.type == "meta" and phased.shape == (24, 4, 3, 3)
    assert mode.mixed == []


def test_only_a_cpu_runs_the_phase_form(monkeypatch: pytest.MonkeyPatch) -> None:
    """Off the CPU (a GPU; the meta device here) the plain convolution and pool run: the phase form
    only adds kernel launches there."""
    def refuse(conv: nn.Conv2d) -> None:
        raise AssertionError("the phase form ran off the CPU")

    monkeypatch.setattr("visfly_dist.training.conv_pool.phase_params", refuse)
    conv = nn.Conv2d(1, 6, 5).to("meta")
    out = conv_maxpool2(torch.empty(4, 1, 64, 64, device="meta"), conv)
    assert out.shape == (4, 6, 30, 30) and out.device.type == "meta"
    with pytest.raises(AssertionError, match="phase form"):
        conv_maxpool2(torch.rand(4, 1, 64, 64), nn.Conv2d(1, 6, 5))  # the CPU does
