"""The in-memory scene: named objects with world-frame meshes, flight bounds and metadata.

World frame is z-up (ENU), metres. Every object keeps its identity (``object_id`` >= 1, used as
its segmentation id; 0 means nothing) and its visual (face/vertex colours or textures) for RGB.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh


@dataclass
class SceneObject:
    """One object of a scene.

    Attributes:
        name: human-readable name, unique within the scene.
        object_id: segmentation id, >= 1, unique within the scene.
        mesh: triangle mesh in world coordinates (z-up, metres), with its visual.
    """

    name: str
    object_id: int
    mesh: trimesh.Trimesh


@dataclass
class Scene:
    """A static world the drones fly in.

    Attributes:
        name: identifier (generator spec or file stem).
        objects: the obstacles (floor, walls and ceiling included).
        bounds: ``(2, 3)`` box ``[low, high]`` the drones may fly in; leaving it ends an episode.
        metadata: plain data (JSON-able): ``kind``, ``seed``, generator parameters, and optional
            regions as ``(2, 3)`` lists, e.g. ``start_region``, ``goal_region``, ``pad_center``.
    """

    name: str
    objects: list[SceneObject]
    bounds: np.ndarray
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.bounds = np.asarray(self.bounds, dtype=np.float64).reshape(2, 3)
        ids = [o.object_id for o in self.objects]
        assert len(set(ids)) == len(ids) and all(i >= 1 for i in ids), "object ids must be unique and >= 1"

    @property
    def num_triangles(self) -> int:
        return int(sum(len(o.mesh.faces) for o in self.objects))

    def combined_mesh(self) -> trimesh.Trimesh:
        """All objects as one mesh (visuals dropped)."""
        return trimesh.util.concatenate([trimesh.Trimesh(o.mesh.vertices, o.mesh.faces, process=False) for o in self.objects])

    def triangle_object_ids(self) -> np.ndarray:
        """Object id of each triangle of :meth:`combined_mesh`, ``(F,)`` uint16."""
        return np.concatenate([np.full(len(o.mesh.faces), o.object_id, dtype=np.uint16) for o in self.objects])

    def object_by_id(self, object_id: int) -> SceneObject:
        for o in self.objects:
            if o.object_id == object_id:
                return o
        raise KeyError(object_id)
