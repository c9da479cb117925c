"""Surface colour at ray hits, for tracing renderers: textures at the hit's UV, or plain colours.

A hit is ``(geometry id, primitive id, u, v)`` as Embree reports it: the triangle's geometry (one
per mesh, or 0 when every mesh was put into one geometry), the triangle within it, and the hit's
barycentric coordinates (``point = (1 - u - v) * a + u * b + v * c`` for corners ``a, b, c``).

- Textured meshes: the base colour texture is sampled at the hit's UV, bilinearly between texel
  centres with repeat wrapping (glTF's default sampler), times the material's base colour factor.
  UVs follow trimesh's convention (v up; trimesh flips glTF's on load), so ``v = 1`` is the image's
  top row.
- Untextured meshes: face colours (flat) or vertex colours (interpolated with the barycentrics).
- Meshes without a visual are mid grey.

:class:`SurfaceShader` gives the unlit colour; :func:`shade_rgb` adds the shared light of
:mod:`render_base` (two-sided Lambert plus ambient) and the sky for misses, for one camera's image.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import trimesh

from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.scene_worker.camera_math import camera_world_poses, pixel_rays
from visfly_dist.scene_worker.render_common import AMBIENT, LIGHT_DIRECTION

GREY = 128.0


class SurfaceShader:
    """Unlit colours of hits on a list of meshes (module docstring).

    Args:
        meshes: the meshes in geometry-id order; primitive ids index their faces. With
            ``single_geometry=True`` (all meshes in one Embree geometry) primitive ids index the
            concatenation of every mesh's faces and the geometry id is ignored.
    """

    def __init__(self, meshes: Sequence[trimesh.Trimesh], single_geometry: bool = True) -> None:
        self.single_geometry = single_geometry
        self.offsets = np.cumsum([0] + [len(m.faces) for m in meshes]).astype(np.int64)
        total = int(self.offsets[-1])
        self.corner_rgb = np.full((total, 3, 3), GREY, np.float32)   # untextured faces' corner colours
        self.normals = np.zeros((total, 3), np.float64)
        vertex_starts = np.cumsum([0] + [len(m.vertices) for m in meshes])
        self.vertices = np.concatenate([np.zeros((0, 3))] + [np.asarray(m.vertices, np.float64) for m in meshes])
        self.face_vertices = np.concatenate([np.zeros((0, 3), np.int64)]
                                            + [m.faces + s for m, s in zip(meshes, vertex_starts)]).astype(np.int64)
        self._textures: list[tuple[int, int, np.ndarray, np.ndarray, np.ndarray]] = []   # start, stop, uv, image, factor
        for mesh, start in zip(meshes, self.offsets[:-1]):
            stop = start + len(mesh.faces)
            self.normals[start:stop] = mesh.face_normals
            texture = _texture(mesh)
            if texture is not None:
                self._textures.append((int(start), int(stop), *texture))
            else:
                self.corner_rgb[start:stop] = _corner_colors(mesh)
        self._texture_starts = np.array([t[0] for t in self._textures], np.int64)
        flat = not self._textures and bool(np.all(self.corner_rgb == self.corner_rgb[:, :1]))
        self._flat_tables: dict[tuple[int, ...], np.ndarray] | None = {} if flat else None

    def flat_table(self, sky: Sequence[int]) -> np.ndarray | None:
        """Lit colour per face + 1 ``(F + 1, 3)`` uint8 (row 0: ``sky``) when every face is one colour, else None."""
        if self._flat_tables is None:
            return None
        key = tuple(int(c) for c in sky)
        if key not in self._flat_tables:
            lit = self.corner_rgb[:, 0] * _light(self.normals)[:, None]
            self._flat_tables[key] = np.concatenate([np.asarray([key], np.float64), lit]).round().astype(np.uint8)
        return self._flat_tables[key]

    def faces(self, geometry_id: np.ndarray, primitive_id: np.ndarray) -> np.ndarray:
        """Global face index of each hit (``-1`` stays ``-1``: a miss)."""
        primitive_id = np.asarray(primitive_id, dtype=np.int64)
        if self.single_geometry:
            return primitive_id
        return np.where(primitive_id >= 0, self.offsets[np.maximum(geometry_id, 0)] + primitive_id, -1)

    def colors(self, face: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Unlit RGB ``(k, 3)`` float32 in ``[0, 255]`` of hits on global faces ``face`` (>= 0) at ``(u, v)``."""
        face = np.asarray(face, dtype=np.int64)
        bary = np.stack([1.0 - u - v, u, v], axis=-1).astype(np.float32)
        out = np.einsum("kc,kcj->kj", bary, self.corner_rgb[face])
        if self._textures:
            which = np.searchsorted(self._texture_starts, face, side="right") - 1
            for t, (start, stop, uv, image, factor) in enumerate(self._textures):
                rows = np.flatnonzero((which == t) & (face < stop))
                if len(rows):
                    local = face[rows] - start
                    at = np.einsum("kc,kcj->kj", bary[rows], uv[local])
                    out[rows] = sample_bilinear(image, at) * factor
        return out


def sample_bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples ``(k, C)`` of ``image`` ``(H, W, C)`` at ``uv`` ``(k, 2)`` (v up, repeat wrap)."""
    h, w = image.shape[:2]
    x = uv[:, 0] * w - 0.5
    y = (1.0 - uv[:, 1]) * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.astype(np.int64) % w, y0.astype(np.int64) % h
    x1, y1 = (x0 + 1) % w, (y0 + 1) % h
    return ((1 - fy) * ((1 - fx) * image[y0, x0] + fx * image[y0, x1])
            + fy * ((1 - fx) * image[y1, x0] + fx * image[y1, x1]))


def shade_rgb(shader: SurfaceShader, camera: CameraSpec, poses: np.ndarray, depth: np.ndarray,
              face: np.ndarray, sky: Sequence[int]) -> np.ndarray:
    """Lit RGB ``(n, H*W, 3)`` uint8 of one camera's image from its traced depth and faces.

    The barycentrics of each hit are recovered from the hit point (``depth`` along the pixel's ray),
    so a tracer that reports only depth and face works too; one that reports ``u, v`` can call
    :meth:`SurfaceShader.colors` directly.

    Args:
        shader: the scene's shader (one geometry).
        camera: the camera traced.
        poses: ``(n, 7)`` drone poses.
        depth: ``(n, H*W)`` z-depth of each pixel's hit.
        face: ``(n, H*W)`` global face index + 1 of each pixel's hit (0: none).
        sky: colour of misses.
    """
    table = shader.flat_table(sky)
    if table is not None:    # flat colours only: no barycentrics needed
        return table[face]
    out = np.empty((*face.shape, 3), np.uint8)
    out[...] = np.asarray(sky, np.uint8)
    agent, pixel = np.nonzero(face)
    if not len(agent):
        return out
    hit_face = face[agent, pixel].astype(np.int64) - 1
    origins, rots = camera_world_poses(poses, camera)
    rays = pixel_rays(camera)[pixel] * depth[agent, pixel, None].astype(np.float64)
    points = origins[agent] + np.einsum("kij,kj->ki", rots[agent], rays)
    u, v = barycentrics(shader.vertices[shader.face_vertices[hit_face]], points)
    lit = shader.colors(hit_face, u, v) * _light(shader.normals[hit_face])[:, None].astype(np.float32)
    out[agent, pixel] = np.clip(np.round(lit), 0, 255).astype(np.uint8)
    return out


def barycentrics(triangles: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric ``(u, v)`` of ``points`` ``(k, 3)`` projected onto ``triangles`` ``(k, 3, 3)``."""
    a = triangles[:, 0]
    e1, e2, p = triangles[:, 1] - a, triangles[:, 2] - a, points - a
    d11, d12, d22 = (np.einsum("ki,ki->k", x, y) for x, y in ((e1, e1), (e1, e2), (e2, e2)))
    p1, p2 = np.einsum("ki,ki->k", p, e1), np.einsum("ki,ki->k", p, e2)
    det = d11 * d22 - d12 * d12
    det = np.where(np.abs(det) > 1e-30, det, 1.0)    # degenerate triangles: the first corner
    return (d22 * p1 - d12 * p2) / det, (d11 * p2 - d12 * p1) / det


def _light(normals: np.ndarray) -> np.ndarray:
    """Brightness under the shared light of :mod:`render_base` (two-sided Lambert plus ambient)."""
    return AMBIENT + (1.0 - AMBIENT) * np.abs(normals @ np.asarray(LIGHT_DIRECTION))


def _texture(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``(corner uv (F, 3, 2), image (H, W, 3) float32, factor (3,))`` of a textured mesh, else None."""
    visual = mesh.visual
    if not isinstance(visual, trimesh.visual.TextureVisuals) or visual.uv is None or len(visual.uv) != len(mesh.vertices):
        return None
    material = visual.material
    image = getattr(material, "baseColorTexture", None) or getattr(material, "image", None)
    if image is None:
        return None
    pixels = np.asarray(image.convert("RGB"), dtype=np.float32)
    factor = getattr(material, "baseColorFactor", None)
    if factor is None:
        factor = getattr(material, "diffuse", None)
    factor = np.ones(3, np.float32) if factor is None else np.asarray(factor, np.float32)[:3] / 255.0
    return np.asarray(visual.uv, np.float64)[mesh.faces], pixels, factor


def _corner_colors(mesh: trimesh.Trimesh) -> np.ndarray:
    """Corner colours ``(F, 3, 3)`` of an untextured mesh: vertex colours, else face colours, else grey."""
    visual = mesh.visual
    if isinstance(visual, trimesh.visual.ColorVisuals):
        kind = visual.kind
        if kind == "vertex":
            return np.asarray(visual.vertex_colors, np.float32)[:, :3][mesh.faces]
        if kind == "face":
            return np.repeat(np.asarray(visual.face_colors, np.float32)[:, None, :3], 3, axis=1)
    if isinstance(visual, trimesh.visual.TextureVisuals) and visual.material is not None:
        color = np.asarray(visual.material.main_color, np.float32)[:3]
        return np.broadcast_to(color, (len(mesh.faces), 3, 3)).copy()
    return np.full((len(mesh.faces), 3, 3), GREY, np.float32)


def face_rgb(mesh: trimesh.Trimesh) -> np.ndarray:
    """Per-face RGB ``(F, 3)`` uint8 of a mesh's visual: the colour at each face's centroid.

    Textures are sampled at the centroid's UV (times the base colour factor), vertex colours
    averaged, face colours taken as they are (see :mod:`visfly_dist.scene_worker.shading`).
    """
    third = np.full(len(mesh.faces), 1.0 / 3.0)
    colors = SurfaceShader([mesh]).colors(np.arange(len(mesh.faces)), third, third)
    return np.clip(np.round(colors), 0, 255).astype(np.uint8)
