"""The in-memory scene: named objects with world-frame meshes, flight bounds and metadata.

World frame is z-up (ENU), metres. Every object keeps its identity (``object_id`` >= 1, used as
its segmentation id; 0 means nothing) and its visual (face/vertex colours or textures) for RGB.

Moving obstacles: an object with a ``motion`` (:mod:`visfly_dist.scenes.motion`) keeps its mesh in
its own local frame, and at time ``t`` it is that mesh translated by ``motion.position(t)``
(translation only, never rotated, as in VisFly). :meth:`Scene.at_time` gives the static scene of
one instant. The scene's metadata lists the moving objects under ``"moving_objects"`` (object id,
name, motion dict, bounding radius) so that a client computes their states with the same function.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
import trimesh

from visfly_dist.scenes.motion import Motion

MOVING_KEY = "moving_objects"
"""Metadata key listing the moving objects: ``[{"object_id", "name", "motion", "radius"}, ...]``."""


@dataclass
class SceneObject:
    """One object of a scene.

    Attributes:
        name: human-readable name, unique within the scene.
        object_id: segmentation id, >= 1, unique within the scene.
        mesh: triangle mesh in world coordinates (z-up, metres), with its visual; for a moving
            object, in its local frame (placed at ``motion.position(t)``).
        motion: the path a moving obstacle follows, or None for a static one.
    """

    name: str
    object_id: int
    mesh: trimesh.Trimesh
    motion: Motion | None = None

    @property
    def bounding_radius(self) -> float:
        """Largest distance of a vertex from the mesh's frame origin, m (a moving object's reach)."""
        return float(np.linalg.norm(self.mesh.vertices, axis=1).max()) if len(self.mesh.vertices) else 0.0

    def placed(self, t: float) -> "SceneObject":
        """This object as a static one at time ``t`` (itself when static)."""
        if self.motion is None:
            return self
        mesh = self.mesh.copy()
        mesh.apply_translation(self.motion.position(float(t)))
        return SceneObject(self.name, self.object_id, mesh)


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
        moving = [{"object_id": o.object_id, "name": o.name, "motion": o.motion.to_dict(), "radius": o.bounding_radius}
                  for o in self.objects if o.motion is not None]  # the moving objects, in order
        if moving:
            self.metadata = {**self.metadata, MOVING_KEY: moving}
        elif MOVING_KEY in self.metadata:
            self.metadata = {k: v for k, v in self.metadata.items() if k != MOVING_KEY}

    @property
    def static_objects(self) -> list[SceneObject]:
        """The objects without a motion, in order."""
        return [o for o in self.objects if o.motion is None]

    @property
    def moving_objects(self) -> list[SceneObject]:
        """The objects with a motion, in order."""
        return [o for o in self.objects if o.motion is not None]

    def at_time(self, t: float) -> "Scene":
        """The static scene of instant ``t``: every moving object placed at its position then."""
        return Scene(self.name, [o.placed(t) for o in self.objects], self.bounds.copy(),
                     {k: v for k, v in self.metadata.items() if k != MOVING_KEY})

    @property
    def num_triangles(self) -> int:
        return int(sum(len(o.mesh.faces) for o in self.objects))

    def combined_mesh(self) -> trimesh.Trimesh:
        """All objects as one mesh (visuals dropped; moving objects in their local frames)."""
        meshes = [trimesh.Trimesh(o.mesh.vertices, o.mesh.faces, process=False) for o in self.objects]
        return cast(trimesh.Trimesh, trimesh.util.concatenate(meshes))  # typed Geometry: meshes make a mesh

    def triangle_object_ids(self) -> np.ndarray:
        """Object id of each triangle of :meth:`combined_mesh`, ``(F,)`` uint16."""
        return np.concatenate([np.full(len(o.mesh.faces), o.object_id, dtype=np.uint16) for o in self.objects])

    def object_by_id(self, object_id: int) -> SceneObject:
        for o in self.objects:
            if o.object_id == object_id:
                return o
        raise KeyError(object_id)
