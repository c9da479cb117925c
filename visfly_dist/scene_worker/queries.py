"""Obstacle queries of a scene worker: nearest obstacle point, distance, collision, inside-ness.

For each drone centre ``p`` (a sphere of ``drone_radius``):

- ``distance``: metric distance from the drone's CENTRE to the nearest obstacle surface, capped at
  the search radius; 0 when the centre is inside a closed obstacle.
- ``nearest``: the world point at ``distance`` from ``p`` towards the nearest surface point, that
  is the nearest surface point itself when it lies within the search radius (so
  ``|nearest - p| == distance`` always, except inside an obstacle, where ``nearest`` is the nearest
  surface point: the way out). In an empty scene the direction is straight down.
- ``inside``: the centre lies inside a closed (watertight) obstacle.
- ``collision``: the sphere touches or overlaps an obstacle: ``true distance <= drone_radius`` or
  ``inside``.

How: python-fcl's distance from one BVH of every triangle to a *point* (a sphere of radius 0) at
the centre, mesh first so FCL reports the world nearest point exactly. Querying the centre as a
point sidesteps FCL's garbage answers for overlapping shapes (a point overlaps nothing unless it
lies on a surface, where the answer is 0 and the point itself), and one distance answers collision
too (a sphere touches a mesh iff its centre is within ``drone_radius`` of a triangle). A sphere
wholly inside a closed obstacle touches no triangle, so inside-ness is its own test: ray parity per
closed object with Embree, the majority of three skewed rays.
"""

from __future__ import annotations

from dataclasses import dataclass

import fcl
import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from visfly_dist.errors import ConfigError
from visfly_dist.scenes.scene import Scene

PARITY_DIRECTIONS = np.array([[0.5377, 0.2841, 0.7938], [-0.6712, 0.4395, -0.5968], [0.1832, -0.9127, 0.3651]])
MAX_CROSSINGS = 512
CROSSING_STEP = 1e-4   # metres a parity ray moves past each surface it crosses


@dataclass(frozen=True)
class QueryResult:
    """Answers for ``n`` drones (see the module docstring for the exact meanings).

    Attributes:
        collision: ``(n,)`` bool, the drone's sphere touches an obstacle or its centre is inside one.
        inside: ``(n,)`` bool, the centre is inside a closed obstacle.
        nearest: ``(n, 3)`` float32 world point towards the nearest obstacle surface.
        distance: ``(n,)`` float32 centre-to-surface distance in ``[0, search_radius]``.
    """

    collision: np.ndarray
    inside: np.ndarray
    nearest: np.ndarray
    distance: np.ndarray


class ObstacleQueries:
    """Nearest-obstacle, collision and inside-ness queries over one scene's meshes.

    Args:
        scene: the obstacles (every object's mesh).
        drone_radius: radius of a drone's collision sphere, metres.
    """

    def __init__(self, scene: Scene, drone_radius: float = 0.1) -> None:
        if not (np.isfinite(drone_radius) and drone_radius >= 0):
            raise ConfigError(f"drone_radius={drone_radius!r} must be a finite number >= 0")
        self.drone_radius = float(drone_radius)
        objects = [o for o in scene.objects if len(o.mesh.faces)]
        self._bvh = self._embree = None
        if not objects:
            return
        starts = np.cumsum([0] + [len(o.mesh.vertices) for o in objects])
        vertices = np.concatenate([o.mesh.vertices for o in objects]).astype(np.float64)
        faces = np.concatenate([o.mesh.faces + s for o, s in zip(objects, starts)]).astype(np.int32)
        model = fcl.BVHModel()
        model.beginModel(len(vertices), len(faces))
        model.addSubModel(vertices, faces)
        model.endModel()
        self._bvh = fcl.CollisionObject(model)
        self._point = fcl.CollisionObject(fcl.Sphere(0.0))
        self._request = fcl.DistanceRequest(enable_nearest_points=True)
        self._closed = np.array([o.mesh.is_watertight for o in objects])
        if self._closed.any():
            self._embree = rtcore_scene.EmbreeScene()
            TriangleMesh(self._embree, vertices[faces].astype(np.float32))
            self._face_object = np.concatenate([np.full(len(o.mesh.faces), i) for i, o in enumerate(objects)])

    def query(self, positions: np.ndarray, search_radius: float) -> QueryResult:
        """Nearest obstacle, distance, collision and inside-ness of drones centred at ``positions``.

        Args:
            positions: ``(n, 3)`` world positions of drone centres.
            search_radius: cap on the reported distance, metres (>= 0).
        """
        positions = _check_positions(positions)
        if not (np.isfinite(search_radius) and search_radius >= 0):
            raise ConfigError(f"search_radius={search_radius!r} must be a finite number >= 0")
        dist, points = self._closest(positions)
        inside = self._inside(positions)
        offset = points - positions
        with np.errstate(invalid="ignore", divide="ignore"):
            unit = np.where(dist[:, None] > 0, offset / dist[:, None], 0.0)
        unit[~np.isfinite(dist)] = (0.0, 0.0, -1.0)
        capped = np.minimum(dist, search_radius)
        nearest = np.where(inside[:, None], points, positions + unit * capped[:, None])
        return QueryResult(
            collision=(dist <= self.drone_radius) | inside,
            inside=inside,
            nearest=nearest.astype(np.float32),
            distance=np.where(inside, 0.0, capped).astype(np.float32),
        )

    def distance(self, positions: np.ndarray) -> np.ndarray:
        """Signed distance ``(n,)`` float64 from each point to the nearest obstacle surface.

        Negative inside a closed obstacle, ``inf`` in an empty scene (for spawn sampling:
        a point is clear when ``distance > clearance + drone_radius``).
        """
        positions = _check_positions(positions)
        dist, _ = self._closest(positions)
        return np.where(self._inside(positions), -dist, dist)

    def _closest(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unsigned distance to and world nearest point on any triangle, per position."""
        n = len(positions)
        dist = np.full(n, np.inf)
        points = positions.copy()
        if self._bvh is None:
            return dist, points
        for i, p in enumerate(positions):
            self._point.setTranslation(p)
            result = fcl.DistanceResult()
            d = fcl.distance(self._bvh, self._point, self._request, result)
            if d > 0:    # 0: the point lies on a surface and is its own nearest point
                dist[i] = d
                points[i] = result.nearest_points[0]
            else:
                dist[i] = 0.0
        return dist, points

    def _inside(self, positions: np.ndarray) -> np.ndarray:
        """Whether each point is inside a closed object: ray parity, majority of three rays."""
        n = len(positions)
        if self._embree is None or n == 0:
            return np.zeros(n, bool)
        votes = np.zeros(n, np.int64)
        for direction in PARITY_DIRECTIONS / np.linalg.norm(PARITY_DIRECTIONS, axis=1, keepdims=True):
            crossings = np.zeros((n, len(self._closed)), np.int64)
            origins = positions.astype(np.float32)
            active = np.arange(n)
            dirs = np.tile(direction.astype(np.float32), (n, 1))
            for _ in range(MAX_CROSSINGS):
                hits = self._embree.run(origins[active], dirs[: len(active)], output=1)
                hit = hits["primID"] >= 0
                active = active[hit]
                if not len(active):
                    break
                np.add.at(crossings, (active, self._face_object[hits["primID"][hit]]), 1)
                origins[active] += (hits["tfar"][hit, None] + np.float32(CROSSING_STEP)) * dirs[: len(active)]
            votes += ((crossings % 2 == 1) & self._closed).any(axis=1)
        return votes >= 2


def _check_positions(positions: np.ndarray) -> np.ndarray:
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ConfigError(f"positions shape {positions.shape} must be (n, 3)")
    if not np.all(np.isfinite(positions)):
        raise ConfigError("positions contain NaN or infinite values; pass finite positions")
    return positions
