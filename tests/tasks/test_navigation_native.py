"""Navigation's native terms (``tasks.native_terms``) against its torch code, and the fallbacks."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from tests.helpers import native_switched_off
from tests.tasks.helpers import hover
from visfly_dist.dynamics import QuadState
from visfly_dist.tasks.common import obstacle_terms
from visfly_dist.tasks import native_terms
from visfly_dist.tasks.native_terms import DISABLE_ENV, goal_geometry, load_tasks
from visfly_dist.tasks.navigation import NavigationEnv, _GoalGeometry

needs_library = pytest.mark.skipif(load_tasks()[0] is None, reason=f"native tasks: {load_tasks()[1]}")
GEOMETRY = ("distance", "target", "heading", "speed", "spin")


def torch_path() -> Any:
    """The task's torch code: the library switched off by its variable, back on after."""
    return native_switched_off(DISABLE_ENV, load_tasks)


def _state(n: int, seed: int) -> tuple[QuadState, torch.Tensor]:
    """``n >= 8`` random agents and goals; the first at their goal, then a level one with signed
    zeros, one in line with its goal, one at rest, one with a strided (transposed) velocity."""
    g = torch.Generator().manual_seed(seed)
    quat = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1)
    pos, omega, goal = (torch.randn(n, 3, generator=g) * 4 for _ in range(3))
    vel = (torch.randn(3, n, generator=g) * 3).T
    goal[:2] = pos[:2]
    quat[2] = torch.tensor([1.0, -0.0, 0.0, -0.0])
    goal[3, :2] = pos[3, :2]
    vel[4], omega[4] = 0.0, 0.0
    state = QuadState(pos, vel, quat, omega, torch.zeros(n, 4), torch.zeros(n, dtype=torch.bool), torch.zeros(n, 0, 4))
    return state, goal


def _assert_geometry_close(got: _GoalGeometry, want: _GoalGeometry) -> None:
    for name in GEOMETRY:
        torch.testing.assert_close(getattr(got, name), getattr(want, name), rtol=2e-7, atol=1e-7, msg=name)


@needs_library
@pytest.mark.parametrize("n", [8, 256, 1031])
def test_native_geometry_matches_torch(n: int) -> None:
    state, goal = _state(n, seed=n)
    with torch.no_grad():
        native = _GoalGeometry(state, goal)
        assert native.distance.grad_fn is None and "_rows" not in vars(native)  # the native path ran
        with torch_path():
            reference = _GoalGeometry(state, goal)
    _assert_geometry_close(native, reference)
    assert torch.equal(native.distance[:2], torch.zeros(2)) and torch.equal(native.target[:2], torch.zeros(2, 4))
    # what the native call leaves out is computed from torch on first use, bit for bit
    assert torch.equal(native.direction, reference.direction) and torch.equal(native.rotmat, reference.rotmat)


@needs_library
def test_geometry_with_gradients_or_other_inputs_runs_torch() -> None:
    state, goal = _state(8, seed=0)
    with_grad = dataclasses.replace(state, pos=state.pos.clone().requires_grad_())
    assert _GoalGeometry(with_grad, goal).distance.grad_fn is not None
    assert _GoalGeometry(state, goal).distance.grad_fn is None  # grad mode on, nothing requires grad: native
    double = QuadState(*(t.double() if t.is_floating_point() else t for t in dataclasses.astuple(state)))
    assert goal_geometry(double.pos, double.vel, double.quat, double.omega, goal.double()) is None
    assert goal_geometry(state.pos, state.vel, state.quat[:, :3], state.omega, goal) is None
    with torch.no_grad():
        assert _GoalGeometry(double, goal.double()).distance.dtype == torch.float64


@contextmanager
def _crafted(env: NavigationEnv, n: int, seed: int) -> Iterator[NavigationEnv]:
    """``env`` with ``n`` crafted agents in its hooks' inputs (state, goal, frame, previous distance,
    success and failure), its own put back after. Obstacle cases, agent by agent: not seen (at and
    past the search radius), seen just inside it, at 1 m (``d < near`` false), just inside 1 m, at
    the obstacle (``d = 0``), the last three flying toward +x; the first two agents at their goal."""
    env.reset()  # a frame to start from
    saved = {k: getattr(env, k) for k in ("state", "goal", "frame", "_prev_distance", "success", "failure", "_geometry")}
    state, goal = _state(n, seed)
    g = torch.Generator().manual_seed(seed + 1)
    offset = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1) * torch.rand(n, 1, generator=g) * 2
    radius = env.config.search_radius
    cut = np.float32(radius * 0.999)
    distance = torch.rand(n, generator=g) * radius
    distance[:3] = torch.tensor([radius, float(cut), float(np.nextafter(cut, np.float32(0)))])
    pos, vel = state.pos.clone(), state.vel.clone()  # vel stays strided
    pos[3:6], vel[3:6] = torch.tensor([0.0, 0.5, 1.0]), torch.tensor([1.0, 0.0, 0.0])  # toward their obstacle
    offset[3:6] = torch.tensor([[1.0, 0.0, 0.0], [float(np.nextafter(np.float32(1), np.float32(0))), 0, 0], [0, 0, 0]])
    distance[3:6] = 1.0
    state = dataclasses.replace(state, pos=pos, vel=vel)
    try:
        env.state, env.goal = state, goal
        env.frame = dataclasses.replace(saved["frame"], nearest=pos + offset, distance=distance)
        env._prev_distance = (goal - pos).norm(dim=1) + torch.randn(n, generator=g) * 0.1
        env.success = torch.rand(n, generator=g) < 0.3
        env.failure = ~env.success & (torch.rand(n, generator=g) < 0.3)
        env._geometry = None
        yield env
    finally:
        for k, v in saved.items():
            setattr(env, k, v)


def _hooks(env: NavigationEnv) -> dict[str, torch.Tensor]:
    """What the hooks give on the env's current inputs, computed afresh."""
    env._geometry = None
    return {"reward": env.get_reward(), "success": env.get_success(), "target": env.get_observation()["target"]}


def _assert_hooks_close(native: dict[str, torch.Tensor], reference: dict[str, torch.Tensor], scale: float) -> None:
    """Rewards agree to a few float32 roundings of their largest term, the rest as the geometry."""
    assert torch.equal(native["success"], reference["success"])
    torch.testing.assert_close(native["target"], reference["target"], rtol=2e-7, atol=1e-7)
    torch.testing.assert_close(native["reward"], reference["reward"], rtol=0, atol=4e-7 * scale)


@needs_library
@pytest.mark.parametrize("seed", [0, 1])
def test_native_reward_matches_torch_on_crafted_agents(envs, seed: int) -> None:
    with _crafted(envs("navigation"), 256, seed) as env, torch.no_grad():
        native = _hooks(env)
        assert native["reward"].grad_fn is None
        with torch_path():
            reference = _hooks(env)
        largest = max(env.config.success_bonus, float(reference["reward"].abs().max()))
        _assert_hooks_close(native, reference, largest)
        s, frame = env.state, env.frame
        proximity, approach = obstacle_terms(s.pos, s.vel, frame.nearest, frame.distance, env.config.search_radius)
        assert torch.equal(proximity[:2], torch.zeros(2)) and float(proximity[2]) > 0  # the search radius
        assert float(approach[3]) == 0.0 < float(approach[4]) and float(approach[5]) == 0.0 < float(proximity[5])
        assert bool(env.success.any() and env.failure.any() and native["success"][:2].all())


@needs_library
def test_native_reward_matches_torch_along_an_episode(envs) -> None:
    env = envs("navigation")
    env.reset()
    rng = np.random.default_rng(5)
    with torch.no_grad():
        for _ in range(5):
            env.step(rng.uniform(-0.3, 0.3, (env.num_envs, 4)).astype(np.float32) + hover(env))
            native = _hooks(env)
            with torch_path():
                reference = _hooks(env)
            _assert_hooks_close(native, reference, env.config.success_bonus)


@needs_library
def test_reward_with_gradients_runs_torch(envs) -> None:
    with _crafted(envs("navigation"), 16, seed=3) as env:
        env.state = dataclasses.replace(env.state, vel=env.state.vel.clone().requires_grad_())
        env._geometry = None
        reward = env.get_reward()
        assert reward.grad_fn is not None
        reward.sum().backward()
        assert env.state.vel.grad is not None


def test_disabled_or_missing_library_falls_back(envs, monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """With ``VISFLY_NATIVE_TASKS=0`` or no built library the hooks run torch and say why."""
    state, goal = _state(8, seed=2)
    for setting in ("disabled", "missing"):
        if setting == "disabled":
            monkeypatch.setenv(DISABLE_ENV, "0")
        else:
            monkeypatch.delenv(DISABLE_ENV, raising=False)
            monkeypatch.setattr(native_terms, "LIBRARY_PATH", tmp_path / "libvisfly_tasks.so")
        load_tasks.cache_clear()
        try:
            lib, reason = load_tasks()
            assert lib is None and ("disabled by VISFLY_NATIVE_TASKS=0" if setting == "disabled" else "not built") in reason
            assert goal_geometry(state.pos, state.vel, state.quat, state.omega, goal) is None
            with torch.no_grad():
                geometry = _GoalGeometry(state, goal)
                assert "_rows" in vars(geometry)  # the torch path
                with _crafted(envs("navigation"), 8, seed=4) as env:
                    assert _hooks(env)["reward"].shape == (8,)
        finally:
            monkeypatch.undo()
            load_tasks.cache_clear()
