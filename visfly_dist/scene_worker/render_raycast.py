"""The ``raycast`` backend: Embree primary rays through every pixel centre.

One Embree scene holds every triangle of the scene; a triangle -> object id table gives
segmentation. Moving obstacles: the native tracer keeps the static BVH and traces the moving
objects as Embree instances after it (per-call translations, only their top-level scene
re-committed; :class:`~render_native.NativeInstancedScene`); embreex keeps the static BVH and
builds a small one of the moving objects' translated triangles per call, the nearer hit winning. Two tracers give the same depth (bit for bit) and the same triangle per pixel:

- ``native`` (the fast path): :mod:`render_native`'s packet tracer, 16 rays per call on 4x4 pixel
  tiles, its own threads over every frame of a call, the GIL released once per call;
- ``embreex`` (the fallback when the native library is not built or fails to load): ray directions
  (optical-axis component 1, so the ray parameter is the z-depth) built in numpy for all drones of a
  call from each camera's pixel slopes (a row term plus a column term: no BLAS, whose own threads
  would fight ours), traced one ray at a time in chunks of agents spread over a few threads.

Both start rays on the near plane and cut them at the far plane. RGB is each face's colour
(textures approximated by ``visual.to_color()``) lit by the fixed light of :mod:`render_base`
(two-sided Lambert plus ambient), computed once per face since the light is fixed in the world; it
is shaded from the hit data (triangle, barycentrics) in one function, :meth:`_shade`. Other drones
are spheres intersected analytically (float64) after the Embree pass, the nearer hit winning: by
the native tracer in the same call, or in numpy (:meth:`_overlay_drones`) with embreex.
"""  # noqa: E501

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from visfly_dist.errors import ConfigError
from visfly_dist.host import usable_cores
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.scene_worker import render_native
from visfly_dist.scene_worker.camera_math import camera_world_poses, pixel_rays, pixel_slopes, spheres_in_view
from visfly_dist.scene_worker.render_common import (
    AMBIENT,
    DRONE_RGB,
    LIGHT_DIRECTION,
    SKY_RGB,
    Renderer,
    drone_segmentation_id,
)
from visfly_dist.scene_worker.shading import SurfaceShader, face_rgb, shade_rgb
from visfly_dist.scenes.scene import Scene

__all__ = ["RaycastRenderer", "TRACERS", "default_tracer", "face_rgb", "lambert"]

log = logging.getLogger(__name__)

RAYS_PER_CHUNK = 1 << 15
TRACERS = ("native", "embreex")


def _embreex_scene(triangles: np.ndarray) -> Any:
    """An embreex scene of ``(F, 3, 3)`` float32 triangles, its BVH built now (embreex is untyped)."""
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, triangles)
    scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))
    return scene


def lambert(normals: np.ndarray) -> np.ndarray:
    """Brightness of surfaces with the given unit normals under the shared light (two-sided)."""
    return AMBIENT + (1.0 - AMBIENT) * np.abs(normals @ np.asarray(LIGHT_DIRECTION))


def default_tracer() -> tuple[str, str]:
    """The tracer a raycast renderer uses unless told otherwise, and why."""
    lib, reason = render_native.load_library()
    if lib is not None:
        return "native", "native packet tracer loaded"
    return "embreex", f"embreex fallback: {reason}"


@dataclass
class _Hits:
    """What one camera's rays hit, for ``n`` drones: arrays ``(n, H*W, ...)``."""

    depth: np.ndarray                   # float32 z-depth
    prim: np.ndarray | None = None      # int32 triangle index, -1: none (or a drone)
    uv: np.ndarray | None = None        # float32 (n, HW, 2) barycentrics of the triangle hit
    seg: np.ndarray | None = None       # uint16 ids (native tracer, segmentation cameras)
    drone: np.ndarray | None = None     # int64 index of the drone seen, -1: none
    drone_light: np.ndarray | None = None   # float64 brightness of the drone seen (RGB)

    def triangles(self) -> np.ndarray:
        """:attr:`prim`, which every camera's hits carry but the native tracer's depth and segmentation ones."""
        assert self.prim is not None, "no triangles traced for this camera"
        return self.prim


@dataclass
class _Plan:
    """A validated native render call: the batches to trace, then what :meth:`_finish` needs."""

    poses: np.ndarray
    show_drones: bool
    batches: list


class RaycastRenderer(Renderer):
    """Embree renderer (see the module docstring).

    Args:
        scene: the scene to draw.
        cameras: the cameras mounted on every drone.
        drone_radius: radius of the spheres drawn for other drones, metres.
        threads: tracing threads; default: the CPUs this process may use, at most 8.
        tracer: ``"native"``, ``"embreex"``, or None for the native one when it loads (else embreex).

    Attributes:
        tracer: the tracer in use, ``"native"`` or ``"embreex"``.
        threads: tracing threads.
    """

    name = "raycast"

    def __init__(self, scene: Scene, cameras: Sequence[CameraSpec], drone_radius: float = 0.1,
                 threads: int | None = None, tracer: str | None = None) -> None:
        super().__init__(scene, cameras, drone_radius)
        if threads is None:
            threads = min(8, usable_cores())
        if not isinstance(threads, int) or isinstance(threads, bool) or threads < 1:
            raise ConfigError(f"threads={threads!r} must be an int >= 1")
        if tracer is not None and tracer not in TRACERS:
            raise ConfigError(f"tracer={tracer!r} must be one of {TRACERS} or None (native when built)")
        if tracer == "native" and not render_native.available():
            raise ConfigError(f"tracer 'native' is unavailable: {render_native.load_library()[1]}")
        self.threads = threads
        # Triangle order: the static objects', then each moving object's (local frame), in scene order.
        objects = [o for o in scene.static_objects + scene.moving_objects if len(o.mesh.faces)]
        meshes = [o.mesh for o in objects]
        triangles = (np.concatenate([m.triangles for m in meshes]) if meshes else np.zeros((0, 3, 3))).astype(np.float32)
        self._object_ids = np.concatenate(
            [np.zeros(1, np.uint16)] + [np.full(len(o.mesh.faces), o.object_id, np.uint16) for o in objects])
        moving = scene.moving_objects
        self._part_counts = [sum(len(o.mesh.faces) for o in scene.static_objects)] + [len(o.mesh.faces) for o in moving]
        self._shader = SurfaceShader(meshes) if any(c.kind == "rgb" for c in self.cameras) else None
        self._rays = {c.name: pixel_rays(c) for c in self.cameras}
        self._slopes = {c.name: tuple(s.astype(np.float32) for s in pixel_slopes(c)) for c in self.cameras}
        self._native: render_native.NativeScene | render_native.NativeInstancedScene | None = None
        self._embree: Any = None            # embreex scenes: the static objects', the moving ones' placed
        self._embree_moving: Any = None
        self._pool: ThreadPoolExecutor | None = None
        self.tracer = tracer or default_tracer()[0]
        if self.tracer == "native":
            try:
                self._native = (render_native.NativeInstancedScene(triangles, self._part_counts,
                                                                   np.array([o.mesh.bounds for o in moving]))
                                if moving else render_native.NativeScene(triangles))
            except RuntimeError as exc:
                if tracer == "native":
                    raise
                log.warning("native tracer failed on scene %r (%s); using embreex", scene.name, exc)
                self.tracer = "embreex"
        if self.tracer == "embreex":
            self._static_count = self._part_counts[0]
            self._init_embreex(triangles[:self._static_count])
            self._moving_triangles = triangles[self._static_count:]
        if moving:
            self.place(0.0)

    def _init_embreex(self, triangles: np.ndarray) -> None:
        if len(triangles):
            self._embree = _embreex_scene(triangles)
        self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="raycast") if self.threads > 1 else None

    def _move(self, translations: np.ndarray) -> None:
        """Native: new instance transforms (the top-level BVH only). embreex: a fresh BVH of the
        moving objects' triangles alone, translated (the static BVH is kept)."""
        if isinstance(self._native, render_native.NativeInstancedScene):
            self._native.move(translations)
            return
        shift = np.repeat(translations, self._part_counts[1:], axis=0).astype(np.float32)
        self._embree_moving = _embreex_scene(self._moving_triangles + shift[:, None, :])

    def _release(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
        if self._native is not None:
            self._native.close()
        self._pool = self._embree = self._embree_moving = self._native = None

    def _render(self, poses: np.ndarray, show_drones: bool) -> dict[str, np.ndarray]:
        if self.tracer == "native":
            plan = self._plan(poses, show_drones)
            render_native.trace(plan.batches, self.threads)
            return self._finish(plan)
        out = {}
        for cam in self.cameras:
            hits = self._trace_embreex(cam, poses)
            if show_drones:
                self._add_drones(cam, poses, *camera_world_poses(poses, cam), hits)
            out[cam.name] = self._image(cam, poses, hits)
        return out

    # -- native tracer: plan (batches), trace (render_native.trace, maybe with other scenes), finish --

    def _plan(self, poses: np.ndarray, show_drones: bool,
              mounts: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
              out: dict[str, np.ndarray] | None = None) -> _Plan:
        """The native batches of validated, non-empty ``poses``: one per camera, outputs allocated.

        ``mounts``: each camera's ``camera_world_poses`` of ``poses``, if already computed.
        ``out``: camera name -> ``(n, 1, H, W)`` C-contiguous array that depth and segmentation
        cameras are traced into (their images are then views of it); others get their own.
        """
        assert self.tracer == "native" and self._native is not None
        n = len(poses)
        batches = []
        drawn = show_drones and n > 1 and self.drone_radius > 0
        for c, cam in enumerate(self.cameras):
            origins, rots = camera_world_poses(poses, cam) if mounts is None else mounts[c]
            shape = (n, cam.height, cam.width)
            right, down = self._slopes[cam.name]
            rgb = cam.kind == "rgb"
            dest = None if out is None or rgb else out[cam.name].reshape(shape)  # a view: out is C-contiguous
            batches.append(render_native.Batch(
                self._native, right, down, cam.near, cam.far, origins.astype(np.float32),
                np.ascontiguousarray(rots, dtype=np.float32),
                dest if dest is not None and cam.kind == "depth" else np.empty(shape, np.float32),
                prim=np.empty(shape, np.int32) if rgb else None,
                uv=np.empty((*shape, 2), np.float32) if rgb else None,
                seg_table=self._object_ids if cam.kind == "segmentation" else None,
                seg=(dest if dest is not None else np.empty(shape, np.uint16)) if cam.kind == "segmentation" else None,
                drones=self._native_drones(cam, origins, rots, poses[:, :3]) if drawn else None,
                drone=np.empty(shape, np.int32) if drawn and rgb else None,
                light=np.empty(shape, np.float64) if drawn and rgb else None, focal=cam.focal_px))
        return _Plan(poses, show_drones, batches)

    def _native_drones(self, cam: CameraSpec, origins: np.ndarray, rots: np.ndarray,
                       centres: np.ndarray) -> render_native.Drones:
        local, dist2, visible = self._drones_in_view(cam, origins, rots, centres)
        a, b = np.nonzero(visible)
        right, down = pixel_slopes(cam)
        return render_native.Drones(
            np.searchsorted(a, np.arange(len(centres) + 1)).astype(np.int32), b.astype(np.int32),
            np.ascontiguousarray(local[a, b]), np.ascontiguousarray(dist2[a, b]), self.drone_radius, cam.focal_px,
            right, down, np.ascontiguousarray(rots), np.asarray(LIGHT_DIRECTION, np.float64), AMBIENT)

    def _finish(self, plan: _Plan) -> dict[str, np.ndarray]:
        """The images of a traced plan (drones drawn by the tracer too)."""
        n = len(plan.poses)
        out = {}
        for cam, b in zip(self.cameras, plan.batches):
            pixels = cam.height * cam.width
            flat = lambda a, pixels=pixels: None if a is None else a.reshape(n, pixels, *a.shape[3:])  # noqa: E731
            hits = _Hits(b.depth.reshape(n, pixels), flat(b.prim), flat(b.uv), flat(b.seg), flat(b.drone), flat(b.light))
            out[cam.name] = self._image(cam, plan.poses, hits)
        return out

    # -- shared: drones, images, shading ------------------------------------------------------------

    def _add_drones(self, cam: CameraSpec, poses: np.ndarray, origins: np.ndarray, rots: np.ndarray,
                    hits: _Hits) -> None:
        if len(poses) > 1 and self.drone_radius > 0:
            hits.drone, hits.drone_light = self._overlay_drones(
                cam, self._rays[cam.name], origins, rots, poses[:, :3], hits.depth, cam.kind == "rgb")
            if hits.prim is not None:
                hits.prim[hits.drone >= 0] = -1

    def _image(self, cam: CameraSpec, poses: np.ndarray, hits: _Hits) -> np.ndarray:
        n = len(hits.depth)
        shape = (n, 1, cam.height, cam.width)
        if cam.kind == "depth":
            return hits.depth.reshape(shape)
        if cam.kind == "segmentation":
            seg = hits.seg if hits.seg is not None else self._object_ids[hits.triangles() + 1]
            if hits.drone is not None:
                seen = hits.drone >= 0
                seg[seen] = drone_segmentation_id(hits.drone[seen])
            return seg.reshape(shape)
        rgb = self._shade(cam, poses, hits)
        return np.ascontiguousarray(rgb.reshape(n, cam.height, cam.width, 3).transpose(0, 3, 1, 2))

    def _shade(self, cam: CameraSpec, poses: np.ndarray, hits: _Hits) -> np.ndarray:
        """RGB ``(n, HW, 3)`` uint8 of the hits: the surface colour at the hit (:mod:`shading`: texture
        at the hit's UV, or face/vertex colours) under the fixed light, sky where none; drones in their
        colour under the same light."""
        assert self._shader is not None, "a renderer with an rgb camera has a shader"
        rgb = shade_rgb(self._shader, cam, poses, hits.depth, hits.triangles() + 1, SKY_RGB)
        if hits.drone is not None:
            assert hits.drone_light is not None, "rgb hits carry the drones' light with the drones"
            seen = hits.drone >= 0
            rgb[seen] = (np.asarray(DRONE_RGB) * hits.drone_light[seen][:, None]).round().astype(np.uint8)
        return rgb

    # -- embreex fallback ---------------------------------------------------------------------------

    def _trace_embreex(self, cam: CameraSpec, poses: np.ndarray) -> _Hits:
        """Depth, triangle and barycentrics of one camera on every drone, one ray at a time."""
        n = len(poses)
        m = cam.width * cam.height
        origins, rots = camera_world_poses(poses, cam)
        hits = _Hits(np.full((n, m), cam.far, np.float32), np.full((n, m), -1, np.int32),
                     np.zeros((n, m, 2), np.float32) if cam.kind == "rgb" else None)
        step = max(1, RAYS_PER_CHUNK // m)
        chunks = [slice(i, min(n, i + step)) for i in range(0, n, step)]
        if self._embree is not None or self._embree_moving is not None:
            work = lambda s: self._trace_chunk(cam, origins[s], rots[s], hits, s)  # noqa: E731
            if self._pool is None or len(chunks) == 1:
                for s in chunks:
                    work(s)
            else:
                list(self._pool.map(work, chunks))
        return hits

    def _trace_chunk(self, cam: CameraSpec, origins: np.ndarray, rots: np.ndarray, out: _Hits, s: slice) -> None:
        right, down = self._slopes[cam.name]
        rots = rots.astype(np.float32)
        k, m = len(rots), cam.width * cam.height
        # direction of pixel (i, j) = R @ (1, -right[j], -down[i]): a row term plus a column term
        rows = rots[:, None, :, 0] - down[None, :, None] * rots[:, None, :, 2]       # (k, H, 3)
        cols = -right[None, :, None] * rots[:, None, :, 1]                          # (k, W, 3)
        dirs: np.ndarray = np.empty((k, cam.height, cam.width, 3), np.float32)
        np.add(rows[:, :, None, :], cols[:, None, :, :], out=dirs)
        dirs = dirs.reshape(k, m, 3)
        starts = dirs * np.float32(cam.near)
        starts += origins.astype(np.float32)[:, None, :]
        starts, dirs = starts.reshape(-1, 3), dirs.reshape(-1, 3)
        hits: dict[str, np.ndarray] | None = None
        for scene, offset in ((self._embree, 0), (self._embree_moving, self._static_count)):
            if scene is None:
                continue
            more = scene.run(starts, dirs, dists=np.full(k * m, cam.far - cam.near, np.float32), output=1)
            more["primID"] = np.where(more["primID"] >= 0, more["primID"] + offset, -1)
            if hits is None:
                hits = more
            else:   # the nearer hit wins (a miss has primID -1)
                nearer = (more["primID"] >= 0) & ((hits["primID"] < 0) | (more["tfar"] < hits["tfar"]))
                hits = {key: np.where(nearer, more[key], hits[key]) for key in ("primID", "tfar", "u", "v")}
        assert hits is not None, "traced only where there is a BVH"
        prim = hits["primID"].reshape(k, m)
        out.triangles()[s] = prim
        np.copyto(out.depth[s], np.where(prim >= 0, np.float32(cam.near) + hits["tfar"].reshape(k, m),
                                         np.float32(cam.far)))
        if out.uv is not None:
            hit = prim >= 0
            out.uv[s, :, 0] = np.where(hit, hits["u"].reshape(k, m), 0.0)
            out.uv[s, :, 1] = np.where(hit, hits["v"].reshape(k, m), 0.0)

    def _drones_in_view(self, cam: CameraSpec, origins: np.ndarray, rots: np.ndarray, centres: np.ndarray):
        """Every drone's centre in every camera's frame ``(a, b, 3)``, its squared distance ``(a, b)``,
        and whether camera ``a`` may see drone ``b`` ``(a, b)`` (never its own)."""
        local = np.einsum("aji,abj->abi", rots, centres[None, :, :] - origins[:, None, :])
        dist2 = np.einsum("abi,abi->ab", local, local)
        visible = spheres_in_view(cam, local, self.drone_radius) & ~np.eye(len(centres), dtype=bool)
        return local, dist2, visible

    def _overlay_drones(self, cam: CameraSpec, rays: np.ndarray, origins: np.ndarray, rots: np.ndarray,
                        centres: np.ndarray, depth: np.ndarray, want_light: bool):
        """Intersect every camera's rays with the other drones' spheres; nearer hits overwrite depth.

        Returns the index of the drone seen per pixel (``-1``: none) and, for RGB, its brightness.
        """
        r = self.drone_radius
        f, w, h = cam.focal_px, cam.width, cam.height
        drone = np.full(depth.shape, -1, np.int64)
        light = np.zeros(depth.shape, np.float64) if want_light else None
        local, dist2, visible = self._drones_in_view(cam, origins, rots, centres)
        for a, b in zip(*np.nonzero(visible)):
            c = local[a, b]
            if c[0] - r > 1e-9:      # bounding box of the sphere's image, from its box's corners
                xs = np.array([c[0] - r, c[0] + r])
                ys = np.concatenate([(c[1] - r) / xs, (c[1] + r) / xs])
                zs = np.concatenate([(c[2] - r) / xs, (c[2] + r) / xs])
                j0, j1 = int(np.ceil(0.5 * w - f * ys.max() - 0.5)), int(np.floor(0.5 * w - f * ys.min() - 0.5))
                i0, i1 = int(np.ceil(0.5 * h - f * zs.max() - 0.5)), int(np.floor(0.5 * h - f * zs.min() - 0.5))
                j0, j1, i0, i1 = max(j0, 0), min(j1, w - 1), max(i0, 0), min(i1, h - 1)
                if j0 > j1 or i0 > i1:
                    continue
                ii, jj = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1), indexing="ij")
                pix = (ii * w + jj).ravel()
            else:
                pix = np.arange(len(rays))
            d = rays[pix]
            qa = np.einsum("pi,pi->p", d, d)
            qb = d @ c
            disc = qb * qb - qa * (dist2[a, b] - r * r)
            root = np.sqrt(np.maximum(disc, 0.0))
            t = (qb - root) / qa
            t = np.where(t >= cam.near, t, (qb + root) / qa)      # near side clipped (or camera inside): far side
            hit = (disc >= 0) & (t >= cam.near) & (t < cam.far) & (t < depth[a, pix])
            pix, t = pix[hit], t[hit]
            depth[a, pix] = t
            drone[a, pix] = b
            if light is not None:
                normals = (t[:, None] * d[hit] - c) / r @ rots[a].T
                light[a, pix] = lambert(normals)
        return drone, light
