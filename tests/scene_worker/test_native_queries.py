"""The native closest-point queries against python-fcl: same nearest points and distances; the fallback."""

from __future__ import annotations

import numpy as np
import pytest

from visfly_dist.errors import ConfigError
from visfly_dist.scene_worker import render_native
from visfly_dist.scene_worker.queries import ObstacleQueries
from visfly_dist.scenes import generate_scene
from visfly_dist.scenes.scene import Scene

needs_native = pytest.mark.skipif(not render_native.available(),
                                  reason=f"native library unavailable: {render_native.load_library()[1]}")

RADIUS = 0.1
SEARCH = 2.0
ATOL = 1e-5


def surface_points(scene: Scene, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points on random triangles of the scene, nudged off them by 0 to 1e-4 m along the normal, both sides."""
    mesh = scene.combined_mesh()
    faces = rng.integers(0, len(mesh.faces), n)
    w = rng.dirichlet(np.ones(3), n)
    on = np.einsum("nk,nkd->nd", w, mesh.vertices[mesh.faces[faces]])
    offset = rng.choice([0.0, 1e-7, -1e-7, 1e-4, -1e-4], n)
    return on + offset[:, None] * mesh.face_normals[faces]


def positions(scene: Scene, rng: np.random.Generator) -> np.ndarray:
    """Random points around the scene, points on and next to its surfaces, and points far outside it."""
    low, high = scene.bounds
    around = rng.uniform(low - 1.0, high + 1.0, size=(1500, 3))          # > 1024: the native call uses threads
    far = high + rng.uniform(50.0, 200.0, size=(20, 3)) * rng.choice([-1, 1], size=(20, 3))
    return np.concatenate([around, surface_points(scene, 500, rng), far])


@needs_native
@pytest.mark.parametrize("kind", ["garage-stones", "pillars"])
def test_native_matches_fcl_on_generated_scenes(kind):
    scene = generate_scene(kind, seed=1)
    native, fcl = ObstacleQueries(scene, RADIUS, backend="native"), ObstacleQueries(scene, RADIUS, backend="fcl")
    assert (native.backend, fcl.backend) == ("native", "fcl")
    p = positions(scene, np.random.default_rng(7))

    d_native, d_fcl = native.distance(p), fcl.distance(p)                  # signed, uncapped
    np.testing.assert_allclose(d_native, d_fcl, rtol=0, atol=ATOL)
    assert (d_fcl[-20:] > 40).all()                                        # the far points are far
    assert (np.abs(d_fcl[1500:-20]) <= 1e-4 + 1e-9).all()                  # the surface points are on or next to one

    r_native, r_fcl = native.query(p, SEARCH), fcl.query(p, SEARCH)
    np.testing.assert_allclose(r_native.distance, r_fcl.distance, rtol=0, atol=ATOL)
    np.testing.assert_allclose(r_native.nearest, r_fcl.nearest, rtol=0, atol=ATOL)
    np.testing.assert_array_equal(r_native.collision, r_fcl.collision)
    np.testing.assert_array_equal(r_native.inside, r_fcl.inside)
    assert r_native.collision.any() and (~r_native.collision).any()
    np.testing.assert_allclose(r_native.distance[-20:], SEARCH)            # capped by the search radius
    np.testing.assert_allclose(np.linalg.norm(r_native.nearest[-20:] - p[-20:], axis=1), SEARCH, rtol=1e-5)


@needs_native
def test_empty_scene_native():
    q = ObstacleQueries(Scene("empty", [], np.array([[0, 0, 0], [1, 1, 1]])), RADIUS, backend="native")
    r = q.query(np.array([[0.5, 0.5, 0.5]]), SEARCH)
    assert not r.collision[0] and r.distance[0] == SEARCH
    np.testing.assert_allclose(r.nearest[0], [0.5, 0.5, 0.5 - SEARCH])
    assert q.distance(np.array([[0.5, 0.5, 0.5]]))[0] == np.inf


@needs_native
def test_degenerate_triangles_answer_their_segment_or_point():
    """A triangle with no area is its longest segment (or its one point): no NaN from the face region."""
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [5, 5, 5]])
    line, point = render_native.NativeMesh(vertices, [[0, 1, 2]]), render_native.NativeMesh(vertices, [[3, 3, 3]])
    p = np.array([[0.5, 1, 0], [1.5, 0, -2], [3, 1, 0], [-1, 0, 0], [1, 0, 0]])
    dist, nearest = line.closest(p, threads=1)
    np.testing.assert_allclose(nearest, [[0.5, 0, 0], [1.5, 0, 0], [2, 0, 0], [0, 0, 0], [1, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(dist, [1, 2, np.sqrt(2), 1, 0], atol=1e-12)
    dist, nearest = point.closest(p, threads=2)
    np.testing.assert_allclose(nearest, np.broadcast_to([5.0, 5, 5], (5, 3)))
    np.testing.assert_allclose(dist, np.linalg.norm(p - 5.0, axis=1))


@needs_native
def test_native_mesh_rejects_bad_faces():
    with pytest.raises(RuntimeError, match=r"face index 3 is outside \[0, 3\)"):
        render_native.NativeMesh(np.eye(3), np.array([[0, 1, 3]]))
    with pytest.raises(ConfigError, match="faces shape"):
        render_native.NativeMesh(np.eye(3), np.zeros((0, 3), int))


def test_backend_falls_back_to_fcl_without_the_library(monkeypatch):
    monkeypatch.setattr(render_native, "load_library", lambda: (None, "not built (test)"))
    scene = generate_scene("pillars", seed=0)
    assert ObstacleQueries(scene, RADIUS).backend == "fcl"
    with pytest.raises(ConfigError, match=r"backend 'native' is unavailable: not built \(test\)"):
        ObstacleQueries(scene, RADIUS, backend="native")
    with pytest.raises(ConfigError, match=r"backend='embree' must be one of"):
        ObstacleQueries(scene, RADIUS, backend="embree")
