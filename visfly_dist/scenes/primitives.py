"""Building blocks of the scene generators: coloured boxes and stones, best-candidate placement.

Every function takes its randomness from a ``numpy.random.Generator`` so that a generator seeded
the same way builds identical meshes.
"""

from __future__ import annotations

import functools
from typing import Sequence

import numpy as np
import trimesh
from scipy.spatial import ConvexHull

from visfly_dist.errors import SceneError

Color = Sequence[int]
STONE_PALETTE = np.array(
    [[120, 110, 100], [150, 140, 125], [95, 90, 85], [140, 115, 90], [110, 120, 115], [165, 155, 140]]
)


def colored(mesh: trimesh.Trimesh, color: Color, rng: np.random.Generator | None = None, jitter: int = 0) -> trimesh.Trimesh:
    """Give ``mesh`` opaque face colours ``color`` (RGB), each face shifted by up to ``jitter``."""
    colors = np.tile(np.append(np.asarray(color, dtype=np.int64), 255), (len(mesh.faces), 1))
    if jitter and rng is not None:
        colors[:, :3] += rng.integers(-jitter, jitter + 1, size=(len(mesh.faces), 1))
    mesh.visual = trimesh.visual.ColorVisuals(mesh, face_colors=np.clip(colors, 0, 255).astype(np.uint8))
    return mesh


def box(low: Sequence[float], high: Sequence[float], color: Color) -> trimesh.Trimesh:
    """An axis-aligned box from corner ``low`` to corner ``high`` (12 triangles)."""
    lo, hi = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    assert np.all(hi > lo), (lo, hi)
    mesh = trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))
    return colored(mesh, color)


def shell_boxes(low: Sequence[float] | np.ndarray, high: Sequence[float] | np.ndarray,
                thickness: float = 0.1) -> list[tuple[str, trimesh.Trimesh]]:
    """Floor, ceiling and four walls as thin boxes just outside the box ``[low, high]``."""
    (x0, y0, z0), (x1, y1, z1), t = low, high, thickness
    floor, wall, ceiling = (120, 120, 120), (185, 178, 165), (205, 205, 205)
    return [
        ("floor", box((x0 - t, y0 - t, z0 - t), (x1 + t, y1 + t, z0), floor)),
        ("ceiling", box((x0 - t, y0 - t, z1), (x1 + t, y1 + t, z1 + t), ceiling)),
        ("wall_x_low", box((x0 - t, y0, z0), (x0, y1, z1), wall)),
        ("wall_x_high", box((x1, y0, z0), (x1 + t, y1, z1), wall)),
        ("wall_y_low", box((x0, y0 - t, z0), (x1, y0, z1), wall)),
        ("wall_y_high", box((x0, y1, z0), (x1, y1 + t, z1), wall)),
    ]


def stone(rng: np.random.Generator, center: np.ndarray, radius: float) -> trimesh.Trimesh:
    """A random stone whose vertices lie within ``radius`` of ``center``.

    Half are jittered icospheres (subdivision 1 or 2: 80 or 320 triangles), half convex hulls of
    random points (about 30 triangles); both get a random anisotropic scale, a random rotation and a
    random earthy colour.
    """
    if rng.random() < 0.5:
        vertices, faces = unit_icosphere(int(rng.integers(1, 3)))
        vertices = vertices * rng.uniform(0.85, 1.0, size=(len(vertices), 1))
    else:
        points = rng.normal(size=(18, 3))
        points *= rng.uniform(0.7, 1.0, size=(18, 1)) / np.linalg.norm(points, axis=1, keepdims=True)
        vertices, faces = convex_hull(points)
    transform = trimesh.transformations.random_rotation_matrix(rand=rng.random(3))
    transform[:3, :3] = transform[:3, :3] @ np.diag(radius * rng.uniform(0.6, 1.0, size=3))
    transform[:3, 3] = center
    vertices = vertices @ transform[:3, :3].T + transform[:3, 3]   # a rotation and a positive scale: faces stay outward
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    return colored(mesh, STONE_PALETTE[rng.integers(len(STONE_PALETTE))], rng, jitter=12)


@functools.lru_cache(maxsize=None)
def _icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return np.array(sphere.vertices), np.array(sphere.faces)


def unit_icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of trimesh's unit icosphere (made once per subdivision level, then copied)."""
    vertices, faces = _icosphere(subdivisions)
    return vertices.copy(), faces.copy()


def convex_hull(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and outward faces of the convex hull of ``points`` (``(n, 3)``, in general position).

    Qhull's triangles as ``trimesh.convex.convex_hull`` takes them (same options, zero-area faces
    dropped, each face turned to face away from the area-weighted centre), without building and
    repairing a Trimesh: a stone's hull in a tenth of the time.
    """
    hull = ConvexHull(points, qhull_options="QbB Pp Qt")
    used = np.unique(hull.simplices)
    remap = np.zeros(len(points), dtype=np.int64)
    remap[used] = np.arange(len(used))
    vertices, faces = points[used], remap[hull.simplices]
    corners = vertices[faces]
    crosses = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    norms = np.linalg.norm(crosses, axis=1)
    valid = norms > 1e-12
    faces, crosses, corners, norms = faces[valid], crosses[valid], corners[valid], norms[valid]
    centres = corners.mean(axis=1)
    centroid = np.average(centres, weights=norms / 2, axis=0)
    backwards = np.einsum("ij,ij->i", crosses, centres - centroid) < 0.0
    faces[backwards] = faces[backwards][:, ::-1]
    return vertices, faces


def sphere_hits_box(centers: np.ndarray, radius: float | np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Whether each sphere ``(centers (n,3), radius)`` overlaps the box ``[low, high]``; ``(n,)`` bool."""
    nearest = np.clip(centers, low, high)
    return np.linalg.norm(centers - nearest, axis=1) < radius


def best_candidate(
    rng: np.random.Generator,
    radii: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    keep_clear: Sequence[tuple[np.ndarray, np.ndarray]],
    candidates: int = 12,
    rounds: int = 50,
) -> np.ndarray:
    """Centres for spheres of ``radii`` in ``[low, high]`` by best-candidate (Mitchell) sampling.

    Each sphere in turn draws ``candidates`` uniform points, drops those whose sphere would overlap a
    ``keep_clear`` box, and takes the one whose surface is farthest from the spheres placed so far:
    a Poisson-disc-like spread without a fixed minimum distance.

    Raises:
        SceneError: when ``rounds`` batches in a row found no point clear of the boxes.
    """
    centers = np.empty((len(radii), 3))
    for i, radius in enumerate(radii):
        for _ in range(rounds):
            points = rng.uniform(low, high, size=(candidates, 3))
            clear = np.ones(candidates, dtype=bool)
            for box_low, box_high in keep_clear:
                clear &= ~sphere_hits_box(points, radius, box_low, box_high)
            if clear.any():
                break
        else:
            raise SceneError(
                f"no room for an obstacle of radius {radius:.2f} m in {low.tolist()}..{high.tolist()} outside the "
                f"keep-clear regions {[(lo.tolist(), hi.tolist()) for lo, hi in keep_clear]}; shrink the regions"
            )
        points = points[clear]
        if i:
            gaps = np.linalg.norm(points[:, None] - centers[None, :i], axis=2) - radii[None, :i] - radius
            points = points[[int(np.argmax(gaps.min(axis=1)))]]
        centers[i] = points[0]
    return centers


def to_float32_grid(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Round vertices to float32 values so that saved files (float32) read back identical."""
    mesh.vertices = mesh.vertices.astype(np.float32).astype(np.float64)
    return mesh
