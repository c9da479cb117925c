"""The tensor PPO's normalisation in the native kernels against its torch operations (``Normalizer(native=False)``),
and the inputs and cases that keep to torch."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
import torch
from gymnasium import spaces

from visfly_dist.training.native_kernels import DISABLE_ENV, load_kernels
from visfly_dist.training.tensor_ppo import Normalizer

from tests.helpers import native_switched_off

CPU = torch.device("cpu")
needs_kernels = pytest.mark.skipif(load_kernels()[0] is None, reason=f"native kernels: {load_kernels()[1]}")
SPACE = spaces.Dict({"state": spaces.Box(-np.inf, np.inf, (5,), np.float32),
                     "depth": spaces.Box(0, 20, (1, 4, 4), np.float32),
                     "target": spaces.Box(-np.inf, np.inf, (2, 3), np.float32)})
ONE_ENTRY = spaces.Dict({"state": spaces.Box(-np.inf, np.inf, (17,), np.float32)})


@pytest.fixture
def kernels_switched_off() -> Iterator[None]:
    """``VISFLY_NATIVE_KERNELS=0`` while the test runs, the library's loading forgotten before and after."""
    with native_switched_off(DISABLE_ENV, load_kernels):
        yield


def _pair(space: spaces.Dict, num_envs: int, gamma: float = 0.9) -> tuple[Normalizer, Normalizer]:
    native, reference = Normalizer(space, num_envs, gamma, CPU), Normalizer(space, num_envs, gamma, CPU, native=False)
    assert native._kernels is not None and reference._kernels is None
    return native, reference


def _observations(space: spaces.Dict, rows: int, g: torch.Generator, shift: float) -> dict[str, torch.Tensor]:
    """Rows of each entry, around ``shift`` (a change of it sends some scaled values past the clip)."""
    return {k: torch.randn((rows,) + s.shape, generator=g) * (1 + 3 * torch.rand((), generator=g)) + shift
            for k, s in space.spaces.items()}


def _assert_within_an_ulp(got: torch.Tensor, want: torch.Tensor) -> None:
    assert got.dtype == want.dtype == torch.float32 and got.shape == want.shape
    a, b = got.numpy(), want.numpy()
    assert np.array_equal(np.isnan(a), np.isnan(b))
    assert np.all(np.abs(a - b) <= np.spacing(np.maximum(np.abs(a), np.abs(b)))), np.abs(a - b).max()


def _assert_same_statistics(native: Normalizer, reference: Normalizer) -> None:
    for got, want in ((native._moments, reference._moments), (native.ret_moments, reference.ret_moments)):
        assert got.count == want.count and got.mean.dtype == got.var.dtype == torch.float64
        torch.testing.assert_close(got.mean, want.mean, rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(got.var, want.var, rtol=1e-12, atol=0.0)
    torch.testing.assert_close(native.returns, reference.returns, rtol=1e-12, atol=1e-14)


@needs_kernels
@pytest.mark.parametrize("space", [SPACE, ONE_ENTRY], ids=["three-entries", "one-entry"])
def test_native_observations_match_torch_over_many_steps(space: spaces.Dict) -> None:
    """Batches of 1, 7 and 256 rows, added to the statistics or not (a terminal view), their mean
    moving so that some values clip: the same statistics and, within a float32 ulp, the same values."""
    native, reference = _pair(space, 4)
    g = torch.Generator().manual_seed(0)
    clipped = False
    for step in range(90):
        rows = (1, 7, 256)[step % 3]
        obs = _observations(space, rows, g, shift=50.0 if step >= 60 else 3.0)
        update = step % 4 != 3
        got, want = native.observe(obs, update), reference.observe(obs, update)
        assert list(got) == list(obs)
        for k in obs:
            if k == "depth":  # images pass through untouched
                assert got[k] is obs[k]
            else:
                _assert_within_an_ulp(got[k], want[k])
                clipped |= bool((got[k].abs() == 10.0).any())
        _assert_same_statistics(native, reference)
    assert clipped
    for k, m in native.obs_moments.items():
        torch.testing.assert_close(m.var, reference.obs_moments[k].var, rtol=1e-12, atol=0.0)


@needs_kernels
@pytest.mark.parametrize("num_envs", [1, 7, 256])
def test_native_rewards_match_torch_over_many_steps(num_envs: int) -> None:
    """Returns discounted and restarted where done, their statistics, and the clipped scaled rewards."""
    native, reference = _pair(ONE_ENTRY, num_envs, gamma=0.99)
    g = torch.Generator().manual_seed(num_envs)
    for step in range(120):
        reward = torch.randn(num_envs, generator=g) * (40.0 if step % 17 == 0 else 1.0)
        done = torch.rand(num_envs, generator=g) < 0.1
        got, want = native.reward(reward, done), reference.reward(reward, done)
        _assert_within_an_ulp(got, want)
        _assert_same_statistics(native, reference)
    assert native.returns.dtype == torch.float64 and native.returns.shape == (num_envs,)


@needs_kernels
def test_groups_and_held_agents_match_torch_and_the_statistics_stay_in_step() -> None:
    """A group's rows (the kernels, on the group's returns) and held agents (torch's operations) give
    torch's values, and steps of all agents before and after them still give torch's statistics."""
    native, reference = _pair(SPACE, 6)
    g = torch.Generator().manual_seed(5)
    group = torch.tensor([1, 4, 5])
    for step in range(40):
        reward, done = torch.randn(6, generator=g), torch.rand(6, generator=g) < 0.2
        if step % 5 == 1:  # a group of agents
            args: tuple = (reward[group], done[group], group)
        elif step % 5 == 3:  # agents 2 and 3 held
            held = torch.tensor([False, False, True, True, False, False])
            args = (reward, done & ~held, None, held)
        else:
            args = (reward, done)
        _assert_within_an_ulp(native.reward(*args), reference.reward(*args))
        obs = _observations(SPACE, 6, g, shift=1.0)
        for k in ("state", "target"):
            _assert_within_an_ulp(native.observe(obs)[k], reference.observe(obs)[k])
        _assert_same_statistics(native, reference)


@needs_kernels
def test_inputs_the_kernels_do_not_take_are_normalised_by_torch() -> None:
    """float64 observations and rewards take torch's path (with its dtypes);
    a strided float32 entry is taken natively, with the same values."""
    native, reference = _pair(SPACE, 3)
    g = torch.Generator().manual_seed(2)
    obs = _observations(SPACE, 3, g, shift=1.0)
    for n in (native, reference):
        n.observe(obs)
    double = {k: v.double() for k, v in obs.items()}
    got, want = native.observe(double), reference.observe(double)
    assert got["state"].dtype == torch.float64
    torch.testing.assert_close(got["state"], want["state"], rtol=1e-12, atol=1e-14)
    strided = dict(obs, state=torch.randn(5, 3, generator=g).T)
    assert not strided["state"].is_contiguous()
    _assert_within_an_ulp(native.observe(strided)["state"], reference.observe(strided)["state"])
    reward, done = torch.randn(3, generator=g, dtype=torch.float64), torch.tensor([True, False, False])
    got, want = native.reward(reward, done), reference.reward(reward, done)
    assert got.dtype == torch.float64 and torch.equal(got, want)
    _assert_same_statistics(native, reference)


@needs_kernels
def test_statistics_read_before_a_step_keep_their_values() -> None:
    """A step replaces the statistics' tensors as torch's operations do; what was read stays."""
    native, _ = _pair(SPACE, 2)
    g = torch.Generator().manual_seed(3)
    native.observe(_observations(SPACE, 2, g, shift=1.0))
    native.reward(torch.tensor([1.0, -2.0]), torch.tensor([False, True]))
    before = {k: (m.mean.clone(), m.var.clone(), m.mean, m.var) for k, m in native.obs_moments.items()}
    ret_before = (native.ret_moments.var.clone(), native.ret_moments.var)
    returns = (native.returns.clone(), native.returns)
    native.observe(_observations(SPACE, 2, g, shift=4.0))
    native.reward(torch.tensor([3.0, 0.5]), torch.tensor([False, False]))
    for mean, var, held_mean, held_var in before.values():
        assert torch.equal(mean, held_mean) and torch.equal(var, held_var)
    assert torch.equal(*ret_before) and torch.equal(*returns)
    assert not torch.equal(native.ret_moments.var, ret_before[0])


def test_the_switch_turns_the_kernels_off(kernels_switched_off: None) -> None:
    norm = Normalizer(SPACE, 2, 0.9, CPU)
    assert norm._kernels is None
    out = norm.observe(_observations(SPACE, 2, torch.Generator().manual_seed(0), shift=0.0))
    assert out["target"].shape == (2, 2, 3) and out["target"].dtype == torch.float32
