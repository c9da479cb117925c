"""Obstacle queries against analytic answers: distance, nearest point, collision, inside, cap."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from visfly_dist.errors import ConfigError
from visfly_dist.scene_worker.queries import ObstacleQueries
from visfly_dist.scenes.scene import Scene, SceneObject

RADIUS = 0.1


@pytest.fixture(scope="module")
def queries() -> ObstacleQueries:
    """A closed 2 m cube centred on the origin and an open floor plane at z = -3."""
    cube = trimesh.creation.box((2.0, 2.0, 2.0))
    floor = trimesh.Trimesh([[-10, -10, -3], [10, -10, -3], [10, 10, -3], [-10, 10, -3]], [[0, 1, 2], [0, 2, 3]])
    objects = [SceneObject("cube", 1, cube), SceneObject("floor", 2, floor)]
    scene = Scene("q", objects, np.array([[-9, -9, -2.9], [9, 9, 9]]))
    return ObstacleQueries(scene, drone_radius=RADIUS)


def one(queries: ObstacleQueries, point, search_radius=5.0):
    r = queries.query(np.array([point], dtype=float), search_radius)
    assert r.nearest.dtype == np.float32 and r.distance.dtype == np.float32
    return bool(r.collision[0]), bool(r.inside[0]), r.nearest[0].astype(float), float(r.distance[0])


def test_near_a_face_gives_the_centre_distance_and_the_foot_point(queries):
    collision, inside, nearest, distance = one(queries, [1.7, 0.2, -0.3])
    assert (collision, inside) == (False, False)
    assert distance == pytest.approx(0.7, abs=1e-6)           # from the drone CENTRE, not its sphere
    np.testing.assert_allclose(nearest, [1.0, 0.2, -0.3], atol=1e-6)


def test_near_an_edge_points_at_the_edge(queries):
    _, _, nearest, distance = one(queries, [1.5, 1.5, 0.25])
    assert distance == pytest.approx(np.sqrt(0.5), abs=1e-6)
    np.testing.assert_allclose(nearest, [1.0, 1.0, 0.25], atol=1e-6)


def test_near_the_open_plane(queries):
    collision, inside, nearest, distance = one(queries, [4.0, -5.0, -2.5])
    assert (collision, inside) == (False, False)
    assert distance == pytest.approx(0.5, abs=1e-6)
    np.testing.assert_allclose(nearest, [4.0, -5.0, -3.0], atol=1e-6)


def test_overlapping_sphere_collides_with_the_true_nearest_point(queries):
    collision, inside, nearest, distance = one(queries, [1.06, 0.3, 0.4])
    assert (collision, inside) == (True, False)
    assert distance == pytest.approx(0.06, abs=1e-6)
    np.testing.assert_allclose(nearest, [1.0, 0.3, 0.4], atol=1e-6)


def test_touching_counts_as_collision_and_just_clear_does_not(queries):
    r = queries.query(np.array([[0.0, 0.0, 1.0 + RADIUS - 1e-6], [0.0, 0.0, 1.0 + RADIUS + 1e-4]]), 5.0)
    np.testing.assert_array_equal(r.collision, [True, False])


def test_wholly_inside_a_closed_box_is_inside_and_colliding(queries):
    collision, inside, nearest, distance = one(queries, [0.2, -0.1, 0.0])
    assert (collision, inside) == (True, True)
    assert distance == 0.0
    np.testing.assert_allclose(nearest, [1.0, -0.1, 0.0], atol=1e-6)   # the way out: the nearest face
    assert queries.distance(np.array([[0.2, -0.1, 0.0]]))[0] == pytest.approx(-0.8, abs=1e-6)


def test_far_away_distance_is_capped_along_the_true_direction(queries):
    collision, inside, nearest, distance = one(queries, [3.5, 0.0, 0.5], search_radius=2.0)
    assert (collision, inside) == (False, False)
    assert distance == pytest.approx(2.0)
    np.testing.assert_allclose(nearest, [1.5, 0.0, 0.5], atol=1e-5)
    assert queries.distance(np.array([[3.5, 0.0, 0.5]]))[0] == pytest.approx(2.5, abs=1e-6)


def test_batch_matches_single_queries(queries):
    points = np.random.default_rng(3).uniform(-3, 3, size=(40, 3))
    batch = queries.query(points, 1.5)
    for i, p in enumerate(points):
        collision, inside, nearest, distance = one(queries, p, 1.5)
        assert (batch.collision[i], batch.inside[i]) == (collision, inside)
        assert batch.distance[i] == pytest.approx(distance, abs=1e-6)
        inside_cube = np.all(np.abs(p) < 1.0)
        assert batch.inside[i] == inside_cube
        assert batch.distance[i] <= 1.5


def test_empty_scene_answers_nothing_near():
    q = ObstacleQueries(Scene("empty", [], np.array([[0, 0, 0], [1, 1, 1]])), drone_radius=RADIUS)
    r = q.query(np.array([[0.5, 0.5, 0.5]]), 3.0)
    assert not r.collision[0] and not r.inside[0] and r.distance[0] == 3.0
    np.testing.assert_allclose(r.nearest[0], [0.5, 0.5, -2.5])
    assert q.distance(np.array([[0.5, 0.5, 0.5]]))[0] == np.inf


def test_bad_input_is_refused(queries):
    with pytest.raises(ConfigError, match=r"positions shape \(3,\) must be \(n, 3\)"):
        queries.query(np.zeros(3), 1.0)
    with pytest.raises(ConfigError, match="search_radius=-1.0"):
        queries.query(np.zeros((1, 3)), -1.0)
