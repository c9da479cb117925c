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
    with pytest.raises(SceneError, match=r"leave no room along x \(3 m\), y \(3 m\), z \(3 m\); lower the clearance"):
        sample_free_positions(1, 2.0, "uniform", 0, 1, rng, cube_distance, bounds=[[0, 0, 0], [3, 3, 3]])
    # a ground plane alone (a mesh file's flight box is its bounding box): no clearance would help
    with pytest.raises(SceneError, match=r"has no room to fly along z \(0 m\); a mesh file's flight box is its "
                                         r"bounding box: add the scene's walls or ceiling"):
        sample_free_positions(1, 0.5, "uniform", 0, 1, rng, cube_distance, bounds=[[-500, -500, 0], [500, 500, 0]])
    with pytest.raises(SceneError, match=r"distribution='poisson'.*\['uniform', 'normal'\]"):
        sample_free_positions(1, 0.1, "poisson", 0, 1, rng, cube_distance)
    with pytest.raises(SceneError, match="low a=.*<= high b="):
        sample_free_positions(1, 0.1, "uniform", 1, 0, rng, cube_distance)
    with pytest.raises(SceneError, match=r"a=\[1, 2\] must be a finite scalar or 3-vector"):
        sample_free_positions(1, 0.1, "normal", [1, 2], 1, rng, cube_distance)
    assert sample_free_positions(0, 0.1, "uniform", 0, 1, rng, cube_distance).shape == (0, 3)


class Counted:
    """``cube_distance`` that counts the points it was asked about."""

    def __init__(self) -> None:
        self.points = 0

    def __call__(self, points: np.ndarray) -> np.ndarray:
        self.points += len(points)
        return cube_distance(points)


def test_a_region_outside_the_flight_box_fails_before_any_draw_naming_the_axis():
    distance = Counted()
    bounds = [[-3, -3, 0], [3, 3, 4]]
    with pytest.raises(SceneError, match=r"region \(z in \[5, 6\]\) lies outside the flight box \(z in \[0.5, 3.5\], "
                                         r"the bounds shrunk by the clearance\) on axis z"):
        sample_free_positions(4, 0.5, "uniform", [-1, -1, 5], [1, 1, 6], np.random.default_rng(0), distance,
                              bounds=bounds)
    with pytest.raises(SceneError, match=r"mean z=9 with std 0 lies outside the flight box"):
        sample_free_positions(4, 0.5, "normal", [2, 2, 9], [1, 1, 0], np.random.default_rng(0), distance,
                              bounds=bounds)
    assert distance.points == 0


def test_a_region_within_the_clearance_of_obstacles_fails_after_a_few_hundred_distances():
    distance = Counted()
    with pytest.raises(SceneError, match=r"every point of the region lies within the clearance of obstacles \(none can "
                                         r"be farther than 0.11\d m from one\)"):
        sample_free_positions(1, 0.5, "uniform", [0.5, -0.1, -0.1], [0.6, 0.1, 0.1], np.random.default_rng(0),
                              distance)
    assert distance.points <= 8 ** 3  # the grid only: not 100,000 draws


def test_an_unlucky_region_names_the_constraints_that_rejected_its_draws():
    # Possible (corners of the region are 0.87 m from the cube) but rare: the counts say why it failed.
    with pytest.raises(SceneError, match=r"found only \d+ of 50 positions .* after 640 tries: \d+ fell outside the "
                                         r"flight box .*; \d+ were closer than the clearance to an obstacle \(\d+ of "
                                         r"them inside one; the farthest drawn point was 0.\d+ m from any obstacle\)"):
        sample_free_positions(50, 0.55, "uniform", -1.0, 1.0, np.random.default_rng(0), cube_distance,
                              bounds=[[-1.02, -1.02, -1.02], [3, 3, 0.2]], max_tries=640)
