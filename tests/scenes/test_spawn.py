"""sample_free_positions against an analytic obstacle: a unit cube at the origin."""

from __future__ import annotations

import numpy as np
import pytest

from visfly_dist.errors import SceneError
from visfly_dist.scenes import sample_free_positions

LOW, HIGH = np.full(3, -0.5), np.full(3, 0.5)


def cube_distance(points: np.ndarray) -> np.ndarray:
    """Distance from each point to the cube (0 inside)."""
    return np.linalg.norm(points - np.clip(points, LOW, HIGH), axis=1)


def test_uniform_honours_clearance_and_region():
    rng = np.random.default_rng(0)
    points = sample_free_positions(500, 0.6, "uniform", -2.0, 2.0, rng, cube_distance)
    assert points.shape == (500, 3) and points.dtype == np.float64
    assert np.all(cube_distance(points) >= 0.6)
    assert np.all((points >= -2) & (points <= 2))
    # The region's free part is covered: some points come close to the clearance shell.
    assert cube_distance(points).min() < 0.7
    again = sample_free_positions(500, 0.6, "uniform", -2.0, 2.0, np.random.default_rng(0), cube_distance)
    np.testing.assert_array_equal(points, again)


def test_normal_distribution_and_bounds():
    rng = np.random.default_rng(1)
    mean, std = np.array([3.0, 0.0, 1.0]), np.array([0.3, 0.2, 0.1])
    points = sample_free_positions(4000, 0.1, "normal", mean, std, rng, cube_distance)
    np.testing.assert_allclose(points.mean(axis=0), mean, atol=0.02)
    np.testing.assert_allclose(points.std(axis=0), std, rtol=0.06)

    bounds = [[2.0, -1.0, 0.0], [4.0, 1.0, 2.0]]
    points = sample_free_positions(300, 0.25, "uniform", [0, -2, -1], [5, 2, 3], rng, cube_distance, bounds=bounds)
    assert np.all(points >= [2.25, -0.75, 0.25]) and np.all(points <= [3.75, 0.75, 1.75])


def test_fails_clearly_when_impossible():
    rng = np.random.default_rng(2)
    with pytest.raises(SceneError, match=r"found only 0 of 5 positions with clearance=0.1 m in uniform region a=\[-0.4"):
        sample_free_positions(5, 0.1, "uniform", -0.4, 0.4, rng, cube_distance, max_tries=2000)
    with pytest.raises(SceneError, match="leave no room"):
        sample_free_positions(1, 2.0, "uniform", 0, 1, rng, cube_distance, bounds=[[0, 0, 0], [3, 3, 3]])
    with pytest.raises(SceneError, match=r"distribution='poisson'.*\['uniform', 'normal'\]"):
        sample_free_positions(1, 0.1, "poisson", 0, 1, rng, cube_distance)
    with pytest.raises(SceneError, match="low a=.*<= high b="):
        sample_free_positions(1, 0.1, "uniform", 1, 0, rng, cube_distance)
    with pytest.raises(SceneError, match=r"a=\[1, 2\] must be a finite scalar or 3-vector"):
        sample_free_positions(1, 0.1, "normal", [1, 2], 1, rng, cube_distance)
    assert sample_free_positions(0, 0.1, "uniform", 0, 1, rng, cube_distance).shape == (0, 3)
