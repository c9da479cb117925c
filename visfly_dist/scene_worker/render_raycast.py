"""The ``raycast`` backend: Embree primary rays through every pixel centre.

One Embree scene holds every triangle of the scene; a triangle -> object id table gives
segmentation. Ray directions (optical-axis component 1, so the ray parameter is the z-depth) are
built in the world for all drones of a call from each camera's pixel slopes (a row term plus a
column term: no BLAS, whose own threads would fight ours), started on the near plane, cut at the far
plane, and traced in chunks of agents spread over a few threads (Embree releases the GIL).

RGB is the surface colour at each hit (:mod:`shading`: the texture sampled at the hit's UV, or
face/vertex colours) lit by the fixed light of :mod:`render_base` (two-sided Lambert plus ambient). Other drones are spheres intersected analytically after the
Embree pass, the nearer hit winning.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Sequence

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from visfly_dist.errors import ConfigError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.scene_worker.camera_math import camera_world_poses, pixel_rays, pixel_slopes, spheres_in_view
from visfly_dist.scene_worker.render_base import (
    AMBIENT, DRONE_RGB, LIGHT_DIRECTION, SKY_RGB, Renderer, drone_segmentation_id,
)
from visfly_dist.scene_worker.shading import SurfaceShader, shade_rgb
from visfly_dist.scenes.scene import Scene

RAYS_PER_CHUNK = 1 << 15


def lambert(normals: np.ndarray) -> np.ndarray:
    """Brightness of surfaces with the given unit normals under the shared light (two-sided)."""
    return AMBIENT + (1.0 - AMBIENT) * np.abs(normals @ np.asarray(LIGHT_DIRECTION))


class RaycastRenderer(Renderer):
    """Embree renderer (see the module docstring).

    Args:
        scene: the scene to draw.
        cameras: the cameras mounted on every drone.
        drone_radius: radius of the spheres drawn for other drones, metres.
        threads: tracing threads; default: the CPUs this process may use, at most 8.
    """

    name = "raycast"

    def __init__(self, scene: Scene, cameras: Sequence[CameraSpec], drone_radius: float = 0.1,
                 threads: int | None = None) -> None:
        super().__init__(scene, cameras, drone_radius)
        if threads is None:
            threads = min(8, len(os.sched_getaffinity(0)))
        if not isinstance(threads, int) or threads < 1:
            raise ConfigError(f"threads={threads!r} must be an int >= 1")
        meshes = [o.mesh for o in scene.objects if len(o.mesh.faces)]
        self._embree = None
        if meshes:
            self._embree = rtcore_scene.EmbreeScene()
            TriangleMesh(self._embree, np.concatenate([m.triangles for m in meshes]).astype(np.float32))
        self._object_ids = np.concatenate(
            [np.zeros(1, np.uint16)] + [np.full(len(o.mesh.faces), o.object_id, np.uint16) for o in scene.objects])
        self._shader = SurfaceShader(meshes) if any(c.kind == "rgb" for c in self.cameras) else None
        self._rays = {c.name: pixel_rays(c) for c in self.cameras}
        self._slopes = {c.name: tuple(s.astype(np.float32) for s in pixel_slopes(c)) for c in self.cameras}
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix="raycast") if threads > 1 else None
        if self._embree is not None:  # build the BVH now, not in the first render
            self._embree.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))

    def _release(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
        self._pool = self._embree = None

    def _render(self, poses: np.ndarray, show_drones: bool) -> dict[str, np.ndarray]:
        out = {}
        for cam in self.cameras:
            depth, face, drone, drone_light = self._trace(cam, poses, show_drones)
            shape = (len(poses), 1, cam.height, cam.width)
            if cam.kind == "depth":
                out[cam.name] = depth.reshape(shape)
            elif cam.kind == "segmentation":
                seg = self._object_ids[face]
                if drone is not None:
                    hit = drone >= 0
                    seg[hit] = drone_segmentation_id(drone[hit])
                out[cam.name] = seg.reshape(shape)
            else:
                rgb = shade_rgb(self._shader, cam, poses, depth, face, SKY_RGB)
                if drone is not None:
                    hit = drone >= 0
                    rgb[hit] = (np.asarray(DRONE_RGB) * drone_light[hit][:, None]).round().astype(np.uint8)
                out[cam.name] = np.ascontiguousarray(
                    rgb.reshape(len(poses), cam.height, cam.width, 3).transpose(0, 3, 1, 2))
        return out

    def _trace(self, cam: CameraSpec, poses: np.ndarray, show_drones: bool):
        """Depth ``(n, HW)`` f32, face index + 1 ``(n, HW)`` (0 = none), and the drones hit, if any."""
        n = len(poses)
        rays = self._rays[cam.name]
        origins, rots = camera_world_poses(poses, cam)
        depth = np.full((n, len(rays)), cam.far, np.float32)
        face = np.zeros((n, len(rays)), np.int32)
        step = max(1, RAYS_PER_CHUNK // len(rays))
        chunks = [slice(i, min(n, i + step)) for i in range(0, n, step)]
        if self._embree is not None:
            work = lambda s: self._trace_chunk(cam, origins[s], rots[s], depth[s], face[s])  # noqa: E731
            if self._pool is None or len(chunks) == 1:
                for s in chunks:
                    work(s)
            else:
                list(self._pool.map(work, chunks))
        drone = drone_light = None
        if show_drones and n > 1 and self.drone_radius > 0:
            drone, drone_light = self._overlay_drones(cam, rays, origins, rots, poses[:, :3], depth, cam.kind == "rgb")
            face[drone >= 0] = 0
        return depth, face, drone, drone_light

    def _trace_chunk(self, cam: CameraSpec, origins: np.ndarray, rots: np.ndarray, depth: np.ndarray,
                     face: np.ndarray) -> None:
        right, down = self._slopes[cam.name]
        rots = rots.astype(np.float32)
        k, m = depth.shape
        # direction of pixel (i, j) = R @ (1, -right[j], -down[i]): a row term plus a column term
        rows = rots[:, None, :, 0] - down[None, :, None] * rots[:, None, :, 2]       # (k, H, 3)
        cols = -right[None, :, None] * rots[:, None, :, 1]                          # (k, W, 3)
        dirs = np.empty((k, cam.height, cam.width, 3), np.float32)
        np.add(rows[:, :, None, :], cols[:, None, :, :], out=dirs)
        dirs = dirs.reshape(k, m, 3)
        starts = dirs * np.float32(cam.near)
        starts += origins.astype(np.float32)[:, None, :]
        hits = self._embree.run(starts.reshape(-1, 3), dirs.reshape(-1, 3),
                                dists=np.full(k * m, cam.far - cam.near, np.float32), output=1)
        prim = hits["primID"].reshape(k, m)
        np.add(prim, 1, out=face)
        np.copyto(depth, np.where(prim >= 0, np.float32(cam.near) + hits["tfar"].reshape(k, m), np.float32(cam.far)))

    def _overlay_drones(self, cam: CameraSpec, rays: np.ndarray, origins: np.ndarray, rots: np.ndarray,
                        centres: np.ndarray, depth: np.ndarray, want_light: bool):
        """Intersect every camera's rays with the other drones' spheres; nearer hits overwrite depth.

        Returns the index of the drone seen per pixel (``-1``: none) and, for RGB, its brightness.
        """
        n = len(centres)
        r = self.drone_radius
        f, w, h = cam.focal_px, cam.width, cam.height
        drone = np.full(depth.shape, -1, np.int64)
        light = np.zeros(depth.shape, np.float64) if want_light else None
        local = np.einsum("aji,abj->abi", rots, centres[None, :, :] - origins[:, None, :])   # (a, b, 3)
        dist2 = np.einsum("abi,abi->ab", local, local)
        visible = spheres_in_view(cam, local, r) & ~np.eye(n, dtype=bool)
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
            if want_light:
                normals = (t[:, None] * d[hit] - c) / r @ rots[a].T
                light[a, pix] = lambert(normals)
        return drone, light
