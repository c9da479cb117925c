"""``quat_to_rotmat``'s batched form gives the textbook entries bit for bit, and their gradients."""

from __future__ import annotations

import pytest
import torch

from visfly_dist.dynamics.rotations import quat_from_euler, quat_to_rotmat, rotate


def _entrywise(q: torch.Tensor) -> torch.Tensor:
    w, x, y, z = q.unbind(-1)
    return torch.stack((
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ), dim=-1).reshape(q.shape[:-1] + (3, 3))


def _bits(t: torch.Tensor) -> torch.Tensor:
    return t.view(torch.int32 if t.dtype == torch.float32 else torch.int64)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_matches_the_entrywise_form_bit_for_bit(dtype: torch.dtype) -> None:
    torch.manual_seed(0)
    random = torch.nn.functional.normalize(torch.randn(257, 4, dtype=dtype), dim=1)
    special = torch.tensor([[1.0, 0.0, 0.0, 0.0], [1.0, -0.0, 0.0, -0.0], [0.0, 1.0, 0.0, 0.0],
                            [-0.0, 0.0, -1.0, 0.0], [0.5, -0.5, 0.5, -0.5]], dtype=dtype)
    for q in (random, special, random.reshape(257, 1, 4)):
        assert torch.equal(_bits(quat_to_rotmat(q)), _bits(_entrywise(q)))


def test_rotation_and_gradients() -> None:
    q = quat_from_euler(torch.tensor([[0.0, 0.0, torch.pi / 2]]))
    torch.testing.assert_close(rotate(q, torch.tensor([[1.0, 0.0, 0.0]])), torch.tensor([[0.0, 1.0, 0.0]]),
                               atol=1e-6, rtol=0)
    torch.manual_seed(1)
    q = torch.nn.functional.normalize(torch.randn(9, 4, dtype=torch.float64), dim=1).requires_grad_()
    upstream = torch.randn(9, 3, 3, dtype=torch.float64)
    (grad,) = torch.autograd.grad((quat_to_rotmat(q) * upstream).sum(), q)
    (reference,) = torch.autograd.grad((_entrywise(q) * upstream).sum(), q)
    torch.testing.assert_close(grad, reference, rtol=1e-12, atol=1e-12)
