"""The stones' own convex hull and icosphere give trimesh's triangles, in trimesh's order."""

from __future__ import annotations

import numpy as np
import trimesh

from visfly_dist.scenes.primitives import convex_hull, unit_icosphere
from visfly_dist.scenes.solids import solid_components


def oriented_triangles(vertices: np.ndarray, faces: np.ndarray) -> list[tuple]:
    """Each face as its corners, rotated to start at the smallest (orientation kept), in face order."""
    return [min(tuple(map(tuple, np.roll(t, k, axis=0))) for k in range(3)) for t in np.round(vertices[faces], 9)]


def test_convex_hull_matches_trimesh_face_for_face() -> None:
    rng = np.random.default_rng(0)
    for _ in range(50):
        points = rng.normal(size=(18, 3))
        vertices, faces = convex_hull(points)
        reference = trimesh.convex.convex_hull(points)
        assert oriented_triangles(vertices, faces) == oriented_triangles(np.asarray(reference.vertices), np.asarray(reference.faces))
        _, solid = solid_components(vertices, faces)
        assert solid.all()   # closed and facing outwards


def test_unit_icosphere_is_trimeshs_and_a_fresh_copy() -> None:
    for level in (1, 2):
        vertices, faces = unit_icosphere(level)
        reference = trimesh.creation.icosphere(subdivisions=level, radius=1.0)
        np.testing.assert_array_equal(vertices, reference.vertices)
        np.testing.assert_array_equal(faces, reference.faces)
        vertices *= 2.0
        assert np.allclose(np.linalg.norm(unit_icosphere(level)[0], axis=1), 1.0)
