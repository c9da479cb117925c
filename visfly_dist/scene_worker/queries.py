"""Obstacle queries of a scene worker: nearest obstacle point, distance, collision, inside-ness.

For each drone centre ``p`` (a sphere of ``drone_radius``):

- ``distance``: metric distance from the drone's CENTRE to the nearest obstacle surface, capped at
  the search radius; 0 when the centre is inside a solid obstacle.
- ``nearest``: the world point at ``distance`` from ``p`` towards the nearest surface point, that
  is the nearest surface point itself when it lies within the search radius (so
  ``|nearest - p| == distance`` always, except inside an obstacle, where ``nearest`` is the nearest
  surface point: the way out). In an empty scene the direction is straight down.
- ``inside``: the centre lies inside a solid obstacle: a connected component that is closed on
  merged vertices and faces outwards (:mod:`visfly_dist.scenes.solids`; glTF's split vertices do not
  make a box open).
- ``collision``: the sphere touches or overlaps an obstacle: ``true distance <= drone_radius`` or
  ``inside``.

How: the nearest point of every triangle to the centre as a *point*, which answers collision too (a
sphere touches a mesh iff its centre is within ``drone_radius`` of a triangle). Two backends give
the same answers (float64 maths, exact nearest points): the native library's closest-point query
(:class:`~visfly_dist.scene_worker.render_native.NativeMesh`: Embree's ``rtcPointQuery`` over one
BVH of every triangle, all positions in one C call with the GIL released) when it is built, else
python-fcl's distance from one BVH to a sphere of radius 0 at the centre, mesh first so FCL reports
the world nearest point exactly (a point overlaps nothing unless it lies on a surface, which
sidesteps FCL's garbage answers for overlapping shapes), one FCL call per position. A sphere
wholly inside a solid obstacle touches no triangle, so inside-ness is its own test: ray parity per
solid component with Embree (over the solids' triangles only), the majority of three skewed rays,
cast only from points that can be inside a solid: no farther from a surface than the deepest point
of any solid (half the smallest side of its bounding box) and inside some solid's bounding box.

Cost: the native query is one call per :meth:`ObstacleQueries.query`; FCL has no batched distance,
so its fallback is one FCL call per position (the loop body kept to the call itself). Everything
else (the inside test, the answer arithmetic) is vectorised over positions.

Moving obstacles (translated copies of a local-frame mesh, :mod:`visfly_dist.scenes.scene`): the
static objects are one set of structures as above, and each moving object has its own (nearest
points and solids in its local frame, built once). A query at ``time`` moves the positions into
each object's frame instead of moving the object, only for the positions that object can matter
to (within its bounding radius of the best distance so far), and keeps the nearest answer; a
position inside any moving solid is inside. :meth:`ObstacleQueries.distance` (spawn clearance)
treats each moving object as its whole swept path: points along the path, padded by its bounding
radius.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import fcl
import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh
from scipy.spatial import cKDTree

from visfly_dist.errors import ConfigError
from visfly_dist.host import usable_cores
from visfly_dist.scene_worker import render_native
from visfly_dist.scene_worker.render_common import checked_time
from visfly_dist.scenes.scene import Scene, SceneObject
from visfly_dist.scenes.solids import solid_components

PARITY_DIRECTIONS = np.array([[0.5377, 0.2841, 0.7938], [-0.6712, 0.4395, -0.5968], [0.1832, -0.9127, 0.3651]])
MAX_CROSSINGS = 512
CROSSING_STEP = 1e-4   # metres a parity ray moves past each surface it crosses
BOX_CHECK_CHUNK = 1 << 20   # (position, component) pairs tested per bounding-box chunk
ON_SURFACE_M = 1e-12   # an FCL distance below this is a point on a surface
BACKENDS = ("auto", "native", "fcl")
SWEEP_SPACING = 0.05   # metres between the points that stand for a moving obstacle's swept path
POSITIONS_PER_THREAD = 1024   # native closest-point queries: fewer positions per thread cost more than they save


@dataclass(frozen=True)
class QueryResult:
    """Answers for ``n`` drones (see the module docstring for the exact meanings).

    Attributes:
        collision: ``(n,)`` bool, the drone's sphere touches an obstacle or its centre is inside one.
        inside: ``(n,)`` bool, the centre is inside a solid obstacle.
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
        backend: nearest points from ``"native"`` (the native library's closest-point query),
            ``"fcl"`` (python-fcl), or ``"auto"``: native when the library is available, else FCL.
        threads: most threads of a native query (``None``: this host's usable cores, at most 8);
            a worker passes its share of the host's cores.

    Attributes:
        backend: the nearest-point backend in use, ``"native"`` or ``"fcl"``.
    """

    def __init__(self, scene: Scene, drone_radius: float = 0.1, backend: str = "auto", threads: int | None = None) -> None:
        if not (np.isfinite(drone_radius) and drone_radius >= 0):
            raise ConfigError(f"drone_radius={drone_radius!r} must be a finite number >= 0")
        if backend not in BACKENDS:
            raise ConfigError(f"backend={backend!r} must be one of {BACKENDS}")
        if backend == "native" and not render_native.available():
            raise ConfigError(f"backend 'native' is unavailable: {render_native.load_library()[1]}")
        native = backend == "native" or (backend == "auto" and render_native.available())
        self.backend = "native" if native else "fcl"
        self.drone_radius = float(drone_radius)
        self._max_threads = threads or min(8, usable_cores())
        self._moving = [(ObstacleQueries(Scene(o.name, [SceneObject(o.name, o.object_id, o.mesh)], scene.bounds),
                                         drone_radius, backend), o.motion, o.bounding_radius,
                         cKDTree(o.motion.path_points(SWEEP_SPACING))) for o in scene.objects if o.motion is not None]
        objects = [o for o in scene.static_objects if len(o.mesh.faces)]
        self._bvh: Any = None  # fcl.CollisionObject (fcl is untyped)
        self._embree: Any = None  # embreex's EmbreeScene of the solids (untyped)
        self._native: render_native.NativeMesh | None = None
        if not objects:
            return
        starts = np.cumsum([0] + [len(o.mesh.vertices) for o in objects])
        vertices = np.concatenate([o.mesh.vertices for o in objects]).astype(np.float64)
        faces = np.concatenate([o.mesh.faces + s for o, s in zip(objects, starts)]).astype(np.int32)
        self._build_parity(vertices, faces, objects)
        if native:
            self._native = render_native.NativeMesh(vertices, faces)
            return
        model = fcl.BVHModel()
        model.beginModel(len(vertices), len(faces))
        model.addSubModel(vertices, faces)
        model.endModel()
        self._bvh = fcl.CollisionObject(model)
        self._point = fcl.CollisionObject(fcl.Sphere(0.0))
        self._request = fcl.DistanceRequest(enable_nearest_points=True)

    def _build_parity(self, vertices: np.ndarray, faces: np.ndarray, objects: list) -> None:
        """Embree scene of the solids' triangles, their component ids and boxes."""
        groups = np.repeat(np.arange(len(objects)), [len(o.mesh.vertices) for o in objects])
        face_component, solid = solid_components(vertices, faces, groups)  # one call for every object
        keep = solid[face_component]
        if not keep.any():
            return
        _, self._face_component = np.unique(face_component[keep], return_inverse=True)
        triangles = vertices[faces[keep]]
        self._num_solids = int(self._face_component.max()) + 1
        low = np.full((self._num_solids, 3), np.inf)
        high = np.full((self._num_solids, 3), -np.inf)
        np.minimum.at(low, self._face_component, triangles.min(axis=1))
        np.maximum.at(high, self._face_component, triangles.max(axis=1))
        self._boxes = (low, high)
        self._max_depth = float(((high - low).min(axis=1) / 2).max())
        # float32 rays in a frame centred on the solids: a scene far from the origin (a georeferenced
        # export, kilometres out) keeps the precision a parity ray needs to step past a surface
        self._parity_origin = (triangles.reshape(-1, 3).min(axis=0) + triangles.reshape(-1, 3).max(axis=0)) / 2
        self._embree = rtcore_scene.EmbreeScene()
        TriangleMesh(self._embree, (triangles - self._parity_origin).astype(np.float32))
        self._directions = (PARITY_DIRECTIONS / np.linalg.norm(PARITY_DIRECTIONS, axis=1, keepdims=True)).astype(np.float32)

    def query(self, positions: np.ndarray, search_radius: float, time: float = 0.0) -> QueryResult:
        """Nearest obstacle, distance, collision and inside-ness of drones centred at ``positions``.

        Args:
            positions: ``(n, 3)`` world positions of drone centres.
            search_radius: cap on the reported distance, metres (>= 0).
            time: simulation time, s: where the moving obstacles are.
        """
        positions = _check_positions(positions)
        _check_search_radius(search_radius)
        time = checked_time(time)
        dist, points = self._closest(positions)
        inside = self._inside(positions, dist)
        self._add_moving(positions, time, dist, points, inside)
        return _answers(positions, dist, points, inside, self.drone_radius, search_radius)

    def _add_moving(self, positions: np.ndarray, time: float, dist: np.ndarray, points: np.ndarray,
                    inside: np.ndarray) -> None:
        """Fold the moving obstacles at ``time`` into the static answers (arrays updated in place)."""
        if not self._moving or not len(positions):
            return
        offsets = np.stack([motion.position(time) for _, motion, _, _ in self._moving])
        radii = np.array([radius for _, _, radius, _ in self._moving])
        # (n, m): where object k can be nearer than the best so far (or hold the point inside)
        reach = np.linalg.norm(positions[:, None, :] - offsets[None], axis=2) - radii <= dist[:, None]
        for k in np.flatnonzero(reach.any(axis=0)).tolist():
            sub, offset = self._moving[k][0], offsets[k]
            near = np.flatnonzero(reach[:, k])
            local = positions[near] - offset
            d, p = sub._closest(local)
            inside[near] |= sub._inside(local, d)
            better = d < dist[near]
            dist[near[better]] = d[better]
            points[near[better]] = p[better] + offset

    def distance(self, positions: np.ndarray) -> np.ndarray:
        """Signed distance ``(n,)`` float64 from each point to the nearest obstacle surface.

        Negative inside a solid obstacle, ``inf`` in an empty scene (for spawn sampling:
        a point is clear when ``distance > clearance + drone_radius``). A moving obstacle counts
        as its whole swept path (module docstring), so a spawn is clear of it at every time.
        """
        positions = _check_positions(positions)
        dist, _ = self._closest(positions)
        signed = np.where(self._inside(positions, dist), -dist, dist)
        for _, _, radius, path in self._moving:   # the swept path: path points padded by the reach
            swept = path.query(positions)[0] - radius
            signed = np.minimum(signed, swept)
        return signed

    def _closest(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unsigned distance to and world nearest point on any triangle, per position."""
        n = len(positions)
        if self._native is not None:
            threads = min(self._max_threads, -(-n // POSITIONS_PER_THREAD))
            return self._native.closest(positions, threads)   # on a surface: 0 and the point itself
        dist = np.full(n, np.inf)
        points = positions.copy()
        if self._bvh is None:
            return dist, points
        bvh, point, request = self._bvh, self._point, self._request
        set_translation, distance, result_type = point.setTranslation, fcl.distance, fcl.DistanceResult
        for i in range(n):
            set_translation(positions[i])
            result = result_type()
            d = distance(bvh, point, request, result)
            if d > ON_SURFACE_M:    # on a surface: its own nearest point (FCL answers a denormal and garbage points)
                dist[i] = d
                points[i] = result.nearest_points[0]
            else:
                dist[i] = 0.0
        return dist, points

    def _inside(self, positions: np.ndarray, dist: np.ndarray) -> np.ndarray:
        """Whether each point (``dist`` from the nearest surface) is inside a solid: ray parity, majority of three."""
        n = len(positions)
        inside = np.zeros(n, bool)
        if self._embree is None or n == 0:
            return inside
        near = np.flatnonzero(dist <= self._max_depth)
        candidates = near[self._in_some_box(positions[near])]
        if not len(candidates):
            return inside
        votes = np.zeros(len(candidates), np.int64)
        for direction in self._directions:
            votes += self._odd_crossings((positions[candidates] - self._parity_origin).astype(np.float32), direction)
        inside[candidates] = votes >= 2
        return inside

    def _in_some_box(self, positions: np.ndarray) -> np.ndarray:
        """Indices of the positions inside at least one solid's bounding box."""
        low, high = self._boxes
        step = max(1, BOX_CHECK_CHUNK // self._num_solids)
        hits = [np.zeros(0, np.int64)]
        for start in range(0, len(positions), step):
            p = positions[start:start + step, None, :]
            hits.append(start + np.flatnonzero(np.all((p >= low) & (p <= high), axis=2).any(axis=1)))
        return np.concatenate(hits)

    def _odd_crossings(self, origins: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Whether a ray from each origin crosses some solid an odd number of times."""
        m = len(origins)
        dirs = np.broadcast_to(direction, (m, 3))
        active = np.arange(m)
        crossings = []
        for _ in range(MAX_CROSSINGS):
            hits = self._embree.run(origins[active], np.ascontiguousarray(dirs[: len(active)]), output=1)
            hit = hits["primID"] >= 0
            active = active[hit]
            if not len(active):
                break
            crossings.append(active * self._num_solids + self._face_component[hits["primID"][hit]])
            at = origins[active] + hits["tfar"][hit, None] * direction
            # past the surface by CROSSING_STEP, or by a few float32 steps where those are coarser (a
            # large scene's far corners): a fixed step there would land on the same surface again
            step = np.maximum(np.float32(CROSSING_STEP), 4 * np.spacing(np.abs(at).max(axis=1)))
            origins[active] = at + step[:, None] * direction
        if not crossings:
            return np.zeros(m, bool)
        keys, counts = np.unique(np.concatenate(crossings), return_counts=True)
        odd = np.zeros(m, bool)
        odd[keys[counts % 2 == 1] // self._num_solids] = True
        return odd


def query_scenes(items: Sequence[tuple[ObstacleQueries, np.ndarray, float]], search_radius: float) -> QueryResult:
    """:meth:`ObstacleQueries.query` of several scenes at once, rows concatenated in item order.

    ``items``: ``(queries, positions (n, 3), time)`` per scene (the time places its moving obstacles).

    The nearest points of every native scene come from ONE native call; the inside test runs only
    for scenes with a position near a solid; the answer arithmetic is vectorised over all rows.
    So a worker holding many scenes of one drone each pays about what one scene of many drones costs.
    """
    _check_search_radius(search_radius)
    times = [checked_time(t) for _, _, t in items]
    counts = [len(p) for _, p, _ in items]
    positions = _check_positions(np.concatenate([np.asarray(p, np.float64).reshape(-1, 3) for _, p, _ in items])
                                 if items else np.zeros((0, 3)))
    ends = np.cumsum(counts)
    starts = ends - counts
    dist = np.full(len(positions), np.inf)
    points = positions.copy()
    native = [(k, q._native) for k, (q, _, _) in enumerate(items) if q._native is not None and counts[k]]
    if native:
        rows = np.concatenate([np.arange(starts[k], ends[k]) for k, _ in native])
        group = np.repeat(np.arange(len(native), dtype=np.int32), [counts[k] for k, _ in native])
        threads = min(items[native[0][0]][0]._max_threads, -(-len(rows) // POSITIONS_PER_THREAD))
        dist[rows], points[rows] = render_native.closest_many([mesh for _, mesh in native], group,
                                                               positions[rows], threads)
    inside = np.zeros(len(positions), bool)
    radius = np.repeat([q.drone_radius for q, _, _ in items], counts) if items else np.zeros(0)
    for k, (q, _, _) in enumerate(items):
        if not counts[k]:
            continue
        span = slice(starts[k], ends[k])
        if q._native is None:
            dist[span], points[span] = q._closest(positions[span])
        if q._embree is not None and (dist[span] <= q._max_depth).any():
            inside[span] = q._inside(positions[span], dist[span])
        if q._moving:
            q._add_moving(positions[span], times[k], dist[span], points[span], inside[span])
    return _answers(positions, dist, points, inside, radius, search_radius)


def _answers(positions: np.ndarray, dist: np.ndarray, points: np.ndarray, inside: np.ndarray,
             drone_radius: float | np.ndarray, search_radius: float) -> QueryResult:
    """The query answers from each position's unsigned distance, nearest surface point and inside-ness."""
    unit = (points - positions) / np.where(dist > 0, dist, 1.0)[:, None]   # 0 on a surface and when empty
    unit[dist == np.inf] = (0.0, 0.0, -1.0)
    capped = np.minimum(dist, search_radius)
    nearest = np.where(inside[:, None], points, positions + unit * capped[:, None])
    return QueryResult(
        collision=(dist <= drone_radius) | inside,
        inside=inside,
        nearest=nearest.astype(np.float32),
        distance=np.where(inside, 0.0, capped).astype(np.float32),
    )


def _check_search_radius(search_radius: float) -> None:
    if not (np.isfinite(search_radius) and search_radius >= 0):
        raise ConfigError(f"search_radius={search_radius!r} must be a finite number >= 0")


def _check_positions(positions: np.ndarray) -> np.ndarray:
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ConfigError(f"positions shape {positions.shape} must be (n, 3)")
    if not np.all(np.isfinite(positions)):
        raise ConfigError("positions contain NaN or infinite values; pass finite positions")
    return positions
