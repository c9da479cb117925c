"""Noise models: statistics against their analytic values, seeding, clamping, validation."""

import pytest
import torch

from visfly_dist.client.noise import NoiseSpec, SensorNoise
from visfly_dist.errors import ConfigError

N = 200_000


def gen(seed=0):
    return torch.Generator().manual_seed(seed)


def test_gaussian_state_noise_has_its_mean_and_std():
    x = torch.full((N, 13), 2.0)
    y = SensorNoise([NoiseSpec("gaussian", {"mean": 0.1, "std": 0.5})], "state")(x, gen())
    d = y - x
    assert d.mean().item() == pytest.approx(0.1, abs=0.005)
    assert d.std().item() == pytest.approx(0.5, rel=0.01)


def test_uniform_state_noise_spans_its_full_width():
    x = torch.zeros(N)
    y = SensorNoise([NoiseSpec("uniform", {"half_width": 0.3})], "state")(x, gen())
    assert y.min().item() == pytest.approx(-0.3, abs=1e-3) and y.max().item() == pytest.approx(0.3, abs=1e-3)
    assert y.std().item() == pytest.approx(0.6 / 12 ** 0.5, rel=0.01)


def test_poisson_noise_has_mean_x_and_variance_x_over_scale():
    x = torch.full((N,), 5.0)
    y = SensorNoise([NoiseSpec("poisson", {"scale": 4.0})], "depth", far=100.0)(x, gen())
    assert y.mean().item() == pytest.approx(5.0, rel=0.01)
    assert y.var().item() == pytest.approx(5.0 / 4.0, rel=0.02)


def test_speckle_noise_is_multiplicative():
    x = torch.full((N,), 10.0)
    y = SensorNoise([NoiseSpec("speckle", {"std": 0.05})], "depth")(x, gen())
    assert (y - x).mean().item() == pytest.approx(0.0, abs=0.005)
    assert (y - x).std().item() == pytest.approx(0.5, rel=0.01)


def test_salt_and_pepper_on_rgb_hits_the_range_ends_at_the_given_rates():
    x = torch.full((N, 3), 100, dtype=torch.uint8)
    y = SensorNoise([NoiseSpec("salt_pepper", {"amount": 0.1, "salt_ratio": 0.3})], "rgb")(x, gen())
    assert y.dtype == torch.uint8
    assert (y == 255).float().mean().item() == pytest.approx(0.03, abs=0.002)
    assert (y == 0).float().mean().item() == pytest.approx(0.07, abs=0.002)
    assert ((y == 100) | (y == 0) | (y == 255)).all()


def test_rgb_gaussian_noise_is_rounded_and_clamped_to_uint8():
    x = torch.full((N,), 250, dtype=torch.uint8)
    y = SensorNoise([NoiseSpec("gaussian", {"std": 20.0})], "rgb")(x, gen())
    assert y.dtype == torch.uint8 and y.max().item() == 255
    assert (y == 255).float().mean().item() == pytest.approx(0.4, abs=0.01)  # P(N(0,20) > 5) = 0.40


def test_depth_noise_is_clamped_to_zero_and_far():
    x = torch.full((N,), 19.9)
    y = SensorNoise([NoiseSpec("gaussian", {"std": 1.0})], "depth", far=20.0)(x, gen())
    assert y.min().item() >= 0.0 and y.max().item() == 20.0


def test_redwood_noise_std_grows_with_the_square_of_depth():
    spec = NoiseSpec("redwood", {"k": 0.002, "subpixel": 1000.0})  # fine quantisation: the Gaussian part shows
    model = SensorNoise([spec], "depth", far=20.0)
    for d in (1.0, 4.0):
        y = model(torch.full((N,), d), gen())
        assert y.mean().item() == pytest.approx(d, abs=0.002 * d * d)
        assert y.std().item() == pytest.approx(0.002 * d * d, rel=0.03)


def test_redwood_quantises_in_disparity_space_and_keeps_far_pixels():
    spec = NoiseSpec("redwood", {"k": 0.0, "baseline_focal": 35.0, "subpixel": 8.0})
    x = torch.linspace(0.5, 15.0, 1000)
    y = SensorNoise([spec], "depth", far=20.0)(torch.cat((x, torch.tensor([20.0]))), gen())
    disparity_steps = 35.0 / y[:-1] * 8.0
    assert torch.allclose(disparity_steps, disparity_steps.round(), atol=1e-3)
    assert (y[:-1] - x).abs().max().item() <= 15.0 ** 2 / (35.0 * 8.0) / 2 + 1e-3  # half a quantisation step
    assert y[-1].item() == 20.0


def test_redwood_dropout_grows_with_distance():
    spec = NoiseSpec("redwood", {"k": 0.0, "subpixel": 1000.0, "dropout": 0.5})
    model = SensorNoise([spec], "depth", far=20.0)
    near = (model(torch.full((N,), 2.0), gen()) == 20.0).float().mean().item()
    far = (model(torch.full((N,), 16.0), gen()) == 20.0).float().mean().item()
    assert near == pytest.approx(0.05, abs=0.003) and far == pytest.approx(0.4, abs=0.005)


def test_same_seed_same_noise_different_seed_different_noise():
    model = SensorNoise([NoiseSpec("gaussian", {"std": 1.0}), NoiseSpec("salt_pepper", {"amount": 0.1})], "depth")
    x = torch.full((1000,), 5.0)
    assert torch.equal(model(x, gen(3)), model(x, gen(3)))
    assert not torch.equal(model(x, gen(3)), model(x, gen(4)))


def test_invalid_specs_are_all_reported():
    specs = [NoiseSpec("blur", {}), NoiseSpec("gaussian", {"sigma": 1.0}), NoiseSpec("redwood", {"k": -1.0}),
             NoiseSpec("salt_pepper", {"amount": 2.0})]
    with pytest.raises(ConfigError) as info:
        SensorNoise(specs, "rgb")
    msg = str(info.value)
    for part in ("'blur' is unknown", "unknown params ['sigma']", "needs param 'std'", "does not apply to a rgb",
                 "k=-1.0", "amount=2.0"):
        assert part in msg
