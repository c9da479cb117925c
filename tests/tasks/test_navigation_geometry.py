"""Navigation's shared goal geometry gives the direct formulas bit for bit, and their gradients."""

from __future__ import annotations

import pytest
import torch

from visfly_dist.dynamics import QuadState
from visfly_dist.dynamics.rotations import quat_to_rotmat
from visfly_dist.tasks.common import body_from_rotmat, target_observation
from visfly_dist.tasks.navigation import _GoalGeometry


def _state(n: int, dtype: torch.dtype) -> tuple[QuadState, torch.Tensor]:
    """``n`` random agents, the first ones at their goal, level with signed zeros, or in line with it."""
    torch.manual_seed(0)
    quat = torch.nn.functional.normalize(torch.randn(max(n, 7), 4, dtype=dtype), dim=1)
    pos, vel, omega, goal = (torch.randn(max(n, 7), 3, dtype=dtype) * 4 for _ in range(4))
    goal[:3] = pos[:3]  # zero distance: the direction clamped
    goal[3:6, :2] = pos[3:6, :2]
    quat[6] = torch.tensor([1.0, -0.0, 0.0, -0.0])
    state = QuadState(pos[:n], vel[:n], quat[:n], omega[:n], torch.zeros(n, 4, dtype=dtype),
                      torch.zeros(n, dtype=torch.bool), torch.zeros(n, 0, 4, dtype=dtype))
    return state, goal[:n]


def _direct(state: QuadState, goal: torch.Tensor) -> dict[str, torch.Tensor]:
    offset = goal - state.pos
    distance = torch.linalg.vector_norm(offset, dim=1)
    direction = offset / distance.clamp(min=1e-6)[:, None]
    rotmat = quat_to_rotmat(state.quat)
    return {"distance": distance, "direction": direction, "rotmat": rotmat,
            "target": torch.cat((body_from_rotmat(rotmat, direction), distance[:, None]), dim=1),
            "speed": torch.linalg.vector_norm(state.vel, dim=1), "spin": torch.linalg.vector_norm(state.omega, dim=1),
            "heading": (rotmat[..., 0] * direction).sum(dim=1)}


def _bits(t: torch.Tensor) -> torch.Tensor:
    return t.contiguous().view(torch.int32 if t.dtype == torch.float32 else torch.int64)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [1, 256, 4099])
def test_geometry_matches_the_direct_formulas_bit_for_bit(dtype: torch.dtype, n: int) -> None:
    state, goal = _state(n, dtype)
    geometry = _GoalGeometry(state, goal)
    for name, expected in _direct(state, goal).items():
        assert torch.equal(_bits(getattr(geometry, name)), _bits(expected)), name
    assert torch.equal(_bits(geometry.target), _bits(target_observation(state.pos, state.quat, goal)))


def test_geometry_gradients_match_the_direct_formulas() -> None:
    state, goal = _state(9, torch.float64)
    leaves = [state.pos.requires_grad_(), state.quat.requires_grad_(), state.vel.requires_grad_(),
              state.omega.requires_grad_()]
    geometry, direct = _GoalGeometry(state, goal), _direct(state, goal)
    torch.manual_seed(1)
    weights = {name: torch.randn_like(t) for name, t in direct.items()}
    for name, w in weights.items():
        got = torch.autograd.grad((getattr(geometry, name) * w).sum(), leaves, retain_graph=True, allow_unused=True)
        want = torch.autograd.grad((direct[name] * w).sum(), leaves, retain_graph=True, allow_unused=True)
        for g, r in zip(got, want):
            assert (g is None) == (r is None), name
            if g is not None:
                torch.testing.assert_close(g, r, rtol=1e-12, atol=1e-12)
