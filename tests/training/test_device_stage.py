"""One packed copy of a step's tensors to the learner's device: the same values, dtypes and shapes."""

from __future__ import annotations

import pytest
import torch

from visfly_dist.training.device_stage import DeviceStage, pack, packed_layout, unpack


def _step_tensors(seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {"obs.depth": torch.rand((5, 1, 9, 7), generator=g), "obs.state": torch.randn((5, 13), generator=g),
            "reward": torch.randn(5, generator=g), "done": torch.rand(5, generator=g) > 0.5,
            "ids": torch.arange(5), "image": torch.randint(0, 255, (5, 3, 3), dtype=torch.uint8, generator=g),
            "scalar": torch.tensor(2.5, dtype=torch.float64), "empty": torch.zeros((0, 4)),
            "strided": torch.randn((4, 6), generator=g)[:, ::2]}


def _assert_same(moved: dict[str, torch.Tensor], tensors: dict[str, torch.Tensor]) -> None:
    assert list(moved) == list(tensors)
    for name, tensor in tensors.items():
        assert moved[name].dtype == tensor.dtype and moved[name].shape == tensor.shape, name
        assert torch.equal(moved[name].cpu(), tensor), name


def test_pack_and_unpack_keep_every_dtype_and_shape() -> None:
    tensors = _step_tensors(0)
    layout, total = packed_layout(tensors)
    assert all(offset % 16 == 0 for *_, offset in layout)
    buffer = torch.zeros(total, dtype=torch.uint8)
    pack(tensors, layout, buffer)
    _assert_same(unpack(buffer, layout), tensors)


def test_cpu_learner_gets_the_tensors_themselves() -> None:
    tensors = _step_tensors(1)
    _assert_same(DeviceStage(torch.device("cpu"))(tensors), tensors)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU torch can use")
def test_cuda_steps_in_turn_keep_their_values() -> None:
    stage = DeviceStage(torch.device("cuda"))
    steps = [_step_tensors(seed) for seed in range(5)]
    moved = [stage(tensors) for tensors in steps]  # pinned buffers reused while earlier copies may run
    for out, tensors in zip(moved, steps):
        assert all(v.device.type == "cuda" for v in out.values())
        _assert_same(out, tensors)
