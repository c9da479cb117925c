"""Which parts of a mesh are solid: closedness on merged vertices, per connected component.

Mesh files split vertices wherever normals or UVs change (every glTF box has 24 vertices, not 8),
so a closed box or sphere looks open to a test on the stored vertices. Here vertices that coincide
(within :data:`MERGE_TOLERANCE`) are merged first; the triangles are then grouped into connected
components (sharing a merged vertex), and a component is **closed** when every one of its edges is
shared by an even number of its triangles (2 for an ordinary closed surface). A component is
**solid** when it is closed and its triangles face outwards (positive signed volume; glTF and most
exporters wind front faces counter-clockwise seen from outside). A solid has an inside: a ray from an
inside point crosses its surface an odd number of times. An open component (a plane, a single wall,
a box with a missing face) has no inside, and neither has a closed shell facing inwards (a room
modelled as one closed box seen from within): its "inside" is where the drones fly. Degenerate
triangles (two corners on the same merged vertex) are ignored.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

MERGE_TOLERANCE = 1e-6
"""Vertices closer than this (metres, per coordinate, on a grid) are the same vertex."""


def solid_components(vertices: np.ndarray, faces: np.ndarray, groups: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Connected components of a triangle mesh and whether each is solid (module docstring).

    Args:
        vertices: ``(V, 3)`` positions.
        faces: ``(F, 3)`` vertex indices.
        groups: ``(V,)`` ints: vertices of different groups are never merged, so several objects
            concatenated into one mesh (one call instead of one per object) keep their components
            apart even where they touch.

    Returns:
        ``(face_component (F,) int64, solid (C,) bool)``: the component of every face (0..C-1)
        and, per component, whether it is solid (closed and facing outwards).
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return np.zeros(0, np.int64), np.zeros(0, bool)
    vertices = np.asarray(vertices, dtype=np.float64)
    keys = np.round(vertices / MERGE_TOLERANCE).astype(np.int64)
    if groups is not None:
        keys = np.column_stack((np.asarray(groups, dtype=np.int64).reshape(-1), keys))
    _, merged = np.unique(keys, axis=0, return_inverse=True)
    f = merged.reshape(-1)[faces]
    n = int(f.max()) + 1
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    graph = coo_matrix((np.ones(len(edges), np.int8), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    used, face_component = np.unique(labels[f[:, 0]], return_inverse=True)

    proper = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
    pf = f[proper]
    pairs = np.sort(np.concatenate([pf[:, [0, 1]], pf[:, [1, 2]], pf[:, [2, 0]]]), axis=1)
    edge_keys, counts = np.unique(pairs[:, 0] * n + pairs[:, 1], return_counts=True)
    open_labels = labels[edge_keys[counts % 2 == 1] // n]
    closed = ~np.isin(used, open_labels)
    face_component = face_component.reshape(-1)
    corners = vertices[faces] - vertices.mean(axis=0)
    volume = np.zeros(len(used))     # six times the signed volume, per component
    np.add.at(volume, face_component, np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])))
    has_proper = np.zeros(len(used), bool)
    has_proper[face_component[proper]] = True
    return face_component, closed & has_proper & (volume > 0)
