"""The native forward of the CTBR step (``dynamics.native_step``) against the NumPy forward."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from visfly_dist.dynamics import DynamicsConfig, Quadrotor
from visfly_dist.dynamics.adjoint import ctbr_step
from visfly_dist.dynamics.native_step import DISABLE_ENV, NativeCtbrStep, load_dynamics
from visfly_dist.dynamics.rotations import quat_from_euler

REPO = Path(__file__).resolve().parents[2]
TOLERANCE = {torch.float32: 1e-6, torch.float64: 1e-12}
needs_library = pytest.mark.skipif(load_dynamics()[0] is None, reason=f"native dynamics: {load_dynamics()[1]}")


def _inputs(quad: Quadrotor, n: int, seed: int) -> tuple[torch.Tensor, ...]:
    """Agents flying and tumbling, some below the ground, rotors off hover, actions partly outside
    [-1, 1]; velocities as a transposed (strided) tensor and rotors as stored by ``initial_state``."""
    g = torch.Generator().manual_seed(seed)
    kw = {"generator": g, "dtype": quad.dtype}
    pos = torch.rand(n, 3, **kw) * torch.tensor([2.0, 2.0, 0.4], dtype=quad.dtype) - 0.1
    vel = (4 * torch.rand(3, n, **kw) - 2).T
    quat = quat_from_euler(1.6 * (torch.rand(n, 3, **kw) - 0.5))
    omega = 4 * torch.rand(n, 3, **kw) - 2
    rotor = quad.hover_rotor_speed() * (0.7 + 0.6 * torch.rand(n, 4, **kw))
    action = 2.4 * torch.rand(n, 4, **kw) - 1.2
    return pos, vel, quat, omega, rotor, action


def _assert_close(got: tuple[torch.Tensor, ...], ref: tuple[torch.Tensor, ...], dtype: torch.dtype) -> None:
    """States agree to ``TOLERANCE`` relative to each component's largest magnitude; contacts exactly."""
    for a, b in zip(got[:5], ref[:5]):
        assert a.dtype == b.dtype == dtype and a.shape == b.shape
        scale = max(1.0, float(b.abs().max()))
        assert float((a - b).abs().max()) <= TOLERANCE[dtype] * scale, (a - b).abs().max()
    assert got[5].dtype == torch.bool and torch.equal(got[5], ref[5])


@needs_library
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [1, 7, 256])
@pytest.mark.parametrize("settings", [
    dict(),
    dict(integrator="euler"),
    dict(motor_lag=False),
    dict(wind=(1.0, -0.5, 0.2), ground=False),
    dict(wind="per-agent", sim_dt=0.01),
])
def test_native_forward_matches_numpy(settings: dict, n: int, dtype: torch.dtype) -> None:
    if settings.get("wind") == "per-agent":
        settings = {**settings, "wind": torch.linspace(-2, 2, 3 * n, dtype=torch.float64).reshape(n, 3)}
    quad = Quadrotor(DynamicsConfig(controller="ctbr", **settings), num_agents=n, dtype=dtype)
    assert quad._adjoint is not None
    native = NativeCtbrStep(quad._adjoint, load_dynamics()[0])
    inputs = _inputs(quad, n, seed=n)
    got = native(*inputs)
    assert got is not None
    ref = ctbr_step(*inputs, quad._adjoint)[0]
    _assert_close(got, ref, dtype)
    if n == 256:
        assert 0 < int(ref[5].sum()) < n  # some agents touched the ground, some did not


@needs_library
def test_native_forward_declines_inputs_it_does_not_take() -> None:
    wind = torch.zeros(4, 3)
    quad = Quadrotor(DynamicsConfig(controller="ctbr", wind=wind), num_agents=4)
    native = NativeCtbrStep(quad._adjoint, load_dynamics()[0])
    inputs = _inputs(quad, 4, seed=1)
    assert native(*inputs) is not None
    assert native(*(x.double() for x in inputs)) is None         # another dtype
    assert native(*(x[:3] for x in inputs)) is None              # not the per-agent wind's N
    assert native(*inputs[:5], inputs[5][:, :3]) is None         # not (N, 4)


def test_loader_disabled_by_env(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(DISABLE_ENV, "0")
    load_dynamics.cache_clear()
    try:
        lib, reason = load_dynamics()
        assert lib is None and reason
        assert Quadrotor(DynamicsConfig(controller="ctbr"), num_agents=2)._native is None
    finally:
        monkeypatch.undo()
        load_dynamics.cache_clear()


ROLLOUT = """
import sys, torch
from visfly_dist.dynamics import DynamicsConfig, Quadrotor
from visfly_dist.dynamics.rotations import quat_from_euler
torch.manual_seed(0)
n, f64 = 64, torch.float64
quad = Quadrotor(DynamicsConfig(controller="ctbr", action_delay_s=0.03), num_agents=n, dtype=f64)
state = quad.initial_state(pos=torch.rand(n, 3, dtype=f64) * 0.3 - 0.05,
                           quat=quat_from_euler(torch.rand(n, 3, dtype=f64) - 0.5))
states = []
with torch.no_grad():
    for k in range(8):
        state = quad.step(state, 2.4 * torch.rand(n, 4, dtype=f64) - 1.2)
        states.append(torch.cat((state.pos, state.vel, state.quat, state.omega, state.rotor,
                                 state.ground_contact[:, None].to(f64)), 1))
torch.save({"native": quad._native is not None, "states": torch.stack(states)}, sys.argv[1])
"""


@needs_library
def test_quadrotor_steps_without_grad_agree_with_and_without_the_library(tmp_path: Path) -> None:
    """The same rollout in two processes, one with the native step and one with it disabled."""
    runs = {}
    for flag in ("1", "0"):
        out = tmp_path / f"native{flag}.pt"
        env = {**os.environ, "PYTHONPATH": str(REPO), DISABLE_ENV: flag, "OMP_NUM_THREADS": "1"}
        subprocess.run([sys.executable, "-c", ROLLOUT, str(out)], env=env, check=True, timeout=120)
        runs[flag] = torch.load(out)
    assert runs["1"]["native"] and not runs["0"]["native"]
    native, numpy = runs["1"]["states"], runs["0"]["states"]
    assert torch.equal(native[..., -1], numpy[..., -1]) and bool(numpy[..., -1].any())
    assert float((native - numpy).abs().max()) <= 1e-11 * float(numpy.abs().max())


@needs_library
def test_steps_with_grad_keep_the_adjoint() -> None:
    quad = Quadrotor(DynamicsConfig(controller="ctbr"), num_agents=3)
    assert quad._native is not None
    action = torch.zeros(3, 4, requires_grad=True)
    state = quad.step(quad.initial_state(), action)
    assert state.pos.grad_fn is not None
    state.pos[:, 2].sum().backward()
    assert action.grad is not None and bool(action.grad[:, 0].gt(0).all())
