"""The ``egl`` backend: every camera of a render call drawn into one framebuffer atlas, one pass.

Per renderer, once: the scene's triangles go into GPU buffers (depth/segmentation: one indexed
vertex buffer of positions, object ids and moving-object indices; RGB: one vertex per triangle
corner with its colour or texture UV and the face normal), the textures into one texel buffer, the
drone sphere into another. The faces are reordered into *chunks* of ``CHUNK_FACES`` (Morton order;
walls and each moving obstacle apart), each with a bounding sphere. A moving obstacle's vertices
carry its index; its translation at the call's time is a texel of a small buffer updated per call
(nothing else is uploaded again).

Per call: every (drone, camera) pair is a *tile* of one atlas (tiles of a camera in columns, about
square; a second pass only when the atlas is full). On the CPU, each tile's camera is tested
against every chunk's bounding sphere; then per camera of the rig one ``glMultiDrawElementsIndirect``
draws each chunk in view once, instanced over the tiles that see it (an instance's attributes are
its tile's world -> eye rows and place in the atlas), and one instanced draw the other drones
(one instance per (tile, drone in its view); a camera's own drone is never drawn). Chunks of
closed solids (watertight, outward winding) are drawn with back faces culled wherever the camera's
near rectangle is clear of their objects' spheres (so a ray can only meet a front face first);
the others, and a camera inside or at a solid, draw both sides. The vertex shader projects with the
tile's camera, then moves the clip coordinates into the tile's rectangle, and four clip distances
cut everything to the tile's frustum, so a triangle never spills into a neighbour. Tiles are
flipped (image row 0 is the tile's bottom GL row), so reading a column back with ``glReadPixels``
gives its tiles' images in output order, straight into the output array (one read per column; RGB
is read as ``(n, H, W, 3)`` and transposed once). Without ``glMultiDrawElementsIndirect`` (GL < 4.3,
or ``VISFLY_EGL_CULL=0``) every tile draws the whole scene, instanced.

On a CPU rasteriser the drones of a call are split between *lanes* (:attr:`BatchEglRenderer.lanes`):
contexts drawing at once, each on its own thread (the process's, shared by its renderers:
:func:`~visfly_dist.scene_worker.render_egl.drawing_lanes`). llvmpipe shades vertices, clips and sets
triangles up on the thread that draws, and that is most of a depth image's cost (the triangles in
view, most smaller than a pixel), so one context keeps one core busy while the raster threads wait
for its frame. On a GPU one lane is enough.

Outputs match the ray tracer: pixels are sampled at their centres (single sample), depth is the
eye-space z computed per fragment in float32 (``far`` where nothing is hit; nothing nearer than
``near``), segmentation is the object id (drone ``k``: ``65535 - k``), and RGB is the surface colour
(face or interpolated vertex colours; textures sampled bilinearly at the UV between texel centres
with repeat wrapping, times the base colour factor, as :mod:`visfly_dist.scene_worker.shading`
does) lit by the shared light of :mod:`render_base` (``AMBIENT + (1 - AMBIENT) |n . l|`` with the face
normal; a drone sphere's normal is exact per pixel) over the sky colour. Drones are icospheres
within 1.8% of ``drone_radius``.

The context is :func:`visfly_dist.scene_worker.render_egl.gl_context` (the device choice is there);
nothing on this path imports pyrender or pyglet, or needs an X11 library.
"""

from __future__ import annotations

import ctypes
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Sequence

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")  # must precede the first OpenGL import

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from visfly_dist.errors import ConfigError  # noqa: E402
from visfly_dist.host import usable_cores  # noqa: E402
from visfly_dist.protocol.cameras import CameraSpec  # noqa: E402
from visfly_dist.scene_worker.camera_math import CAMERA_TO_GL, camera_world_poses, spheres_in_view  # noqa: E402
from visfly_dist.scene_worker.render_common import (  # noqa: E402
    AMBIENT,
    DRONE_RGB,
    LIGHT_DIRECTION,
    SKY_RGB,
    Renderer,
    drone_segmentation_id,
)
from visfly_dist.scene_worker.render_egl import drawing_lanes, gl_context, gl_device  # noqa: E402
from visfly_dist.scenes.scene import Scene  # noqa: E402

DRONE_SUBDIVISIONS = 2   # icosphere of 320 faces: within 1.8% of the radius
CHUNK_FACES = 64          # faces per culling chunk (32-256 measure about the same on llvmpipe)
BIG_FACE_M = 1.0         # faces with a bounding radius above this (m) are chunked apart (walls, floors)
MAX_ATLAS = 8192         # pixels per side of the atlas at most (also capped by the GL limits)
KINDS = ("depth", "segmentation", "rgb")
MIN_TILES_PER_LANE = 8   # fewer drones per lane than this: fewer lanes
MAX_DEFAULT_LANES = 8    # lanes on a CPU rasteriser by default: one per usable core, at most this
_TILE_TEXELS = 4         # per tile: 3 rows of the world -> eye matrix, then (place x, place y, 0, 0)

VERTEX_SHADER = """
layout(location = 0) in vec3 position;
layout(location = 1) in float object_id;
layout(location = 2) in float mover;        // index of the moving object, -1: static
layout(location = 3) in vec3 offset;        // drone instance: sphere centre (scene: constant 0)
layout(location = 4) in vec4 tile_r0;       // per instance: the tile's world -> eye rows ...
layout(location = 9) in vec4 tile_r1;
layout(location = 10) in vec4 tile_r2;
layout(location = 11) in vec4 tile_place;   // ... and its place in the atlas (xy)
#if KIND == 2
layout(location = 5) in vec2 uv;
layout(location = 6) in vec3 colour;        // corner colour, or the texture's factor
layout(location = 7) in vec3 normal;        // face normal
layout(location = 8) in float texture_id;   // -1: no texture
out vec2 v_uv;
out vec3 v_colour;
flat out vec3 v_normal;
flat out float v_texture;
out vec3 v_world;
flat out vec3 v_centre;
#endif
uniform samplerBuffer movers;
uniform bool drones;                        // instances are (tile, drone) pairs, not tiles
uniform vec4 proj;                          // 2f/w, 2f/h, and the z row of the projection
uniform vec2 tile_scale;                    // tile size / atlas size
out float eye_depth;
flat out float seg_id;
void main() {
    vec4 r0 = tile_r0, r1 = tile_r1, r2 = tile_r2, place = tile_place;
    vec3 world = position + offset;
    if (mover >= 0.0) world += texelFetch(movers, int(mover + 0.5)).xyz;
    vec4 w = vec4(world, 1.0);
    vec3 eye = vec3(dot(r0, w), dot(r1, w), dot(r2, w));
    vec4 clip = vec4(proj.x * eye.x, -proj.y * eye.y, proj.z * eye.z + proj.w, -eye.z);  // rows flipped
    gl_ClipDistance[0] = clip.w - clip.x;
    gl_ClipDistance[1] = clip.w + clip.x;
    gl_ClipDistance[2] = clip.w - clip.y;
    gl_ClipDistance[3] = clip.w + clip.y;
    gl_Position = vec4(clip.xy * tile_scale + clip.w * place.xy, clip.zw);
    eye_depth = -eye.z;
    seg_id = object_id;
#if KIND == 2
    v_uv = uv;
    v_colour = colour;
    v_normal = normal;
    v_texture = texture_id;
    v_world = world;
    v_centre = offset;
#endif
}
"""

FRAGMENT_SHADER = """
in float eye_depth;
flat in float seg_id;
#if KIND == 0
layout(location = 0) out float value;      // draw buffer 0: the depth attachment
void main() { value = eye_depth; }
#elif KIND == 1
layout(location = 1) out uint value;       // draw buffer 1: the segmentation attachment
void main() { value = uint(seg_id + 0.5); }
#else
in vec2 v_uv;
in vec3 v_colour;
flat in vec3 v_normal;
flat in float v_texture;
in vec3 v_world;
flat in vec3 v_centre;
uniform samplerBuffer texels;               // every texture's RGBA8 texels, rows top first
uniform isamplerBuffer texture_info;        // per texture: first texel, width, height
uniform bool drones;
uniform vec3 light;
uniform float ambient;
uniform vec3 drone_rgb;
layout(location = 2) out vec4 value;          // draw buffer 2: the RGB attachment
vec3 texel(int first, ivec2 size, int x, int y) {
    x = ((x % size.x) + size.x) % size.x;
    y = ((y % size.y) + size.y) % size.y;
    return texelFetch(texels, first + y * size.x + x).rgb * 255.0;
}
void main() {
    vec3 c = v_colour;
    vec3 n = v_normal;
    if (drones) {
        c = drone_rgb;
        n = normalize(v_world - v_centre);
    } else if (v_texture >= 0.0) {
        ivec4 info = texelFetch(texture_info, int(v_texture + 0.5));
        ivec2 size = info.yz;
        float x = v_uv.x * float(size.x) - 0.5;
        float y = (1.0 - v_uv.y) * float(size.y) - 0.5;
        float x0 = floor(x), y0 = floor(y);
        float fx = x - x0, fy = y - y0;
        int ix = int(x0), iy = int(y0);
        vec3 top = mix(texel(info.x, size, ix, iy), texel(info.x, size, ix + 1, iy), fx);
        vec3 bottom = mix(texel(info.x, size, ix, iy + 1), texel(info.x, size, ix + 1, iy + 1), fx);
        c = mix(top, bottom, fy) * v_colour;
    }
    float lit = ambient + (1.0 - ambient) * abs(dot(n, light));
    value = vec4(c * lit / 255.0, 1.0);
}
#endif
"""

_FORMATS = {  # kind -> (internal format, read format, read type, numpy dtype of one channel)
    "depth": ("GL_R32F", "GL_RED", "GL_FLOAT", np.float32),
    "segmentation": ("GL_R16UI", "GL_RED_INTEGER", "GL_UNSIGNED_SHORT", np.uint16),
    "rgb": ("GL_RGBA8", "GL_RGB", "GL_UNSIGNED_BYTE", np.uint8),
}


def _gl():
    from OpenGL import GL

    return GL


class _Buffer:
    """A GL buffer grown on demand (contents replaced by :meth:`upload`), optionally seen as a texel buffer."""

    def __init__(self, target: int, texture_format: int | None = None) -> None:
        GL = _gl()
        self.target, self.size = target, 0
        self.buffer = GL.glGenBuffers(1)
        self.texture = None
        self.texture_format = texture_format
        if texture_format is not None:
            self.texture = _texture_name()

    def upload(self, data: np.ndarray) -> None:
        GL = _gl()
        data = np.ascontiguousarray(data)
        nbytes = max(int(data.nbytes), 16)
        GL.glBindBuffer(self.target, self.buffer)
        if nbytes > self.size:
            self.size = max(nbytes, 2 * self.size)
            GL.glBufferData(self.target, self.size, None, GL.GL_DYNAMIC_DRAW)
            if self.texture is not None:
                GL.glBindTexture(GL.GL_TEXTURE_BUFFER, self.texture)
                GL.glTexBuffer(GL.GL_TEXTURE_BUFFER, self.texture_format, self.buffer)
        if data.nbytes:
            GL.glBufferSubData(self.target, 0, data.nbytes, data)

    def delete(self) -> None:
        GL = _gl()
        GL.glDeleteBuffers(1, [self.buffer])
        if self.texture is not None:
            GL.glDeleteTextures([self.texture])


def _texture_name() -> int:
    """A new texture name. Through the raw binding: PyOpenGL 3.1.0's ``glGenTextures(1)`` (pyrender
    pins that version) passes a ``byref`` that Python 3.12's ctypes no longer lets it convert."""
    from OpenGL.raw.GL.VERSION.GL_1_1 import glGenTextures

    names = np.zeros(1, np.uint32)
    glGenTextures(1, names)
    return int(names[0])


def _morton(points: np.ndarray) -> np.ndarray:
    """Morton (Z-order) codes of points, 10 bits per axis over their bounding box."""
    low, high = points.min(axis=0), points.max(axis=0)
    q = ((points - low) / np.maximum(high - low, 1e-9) * 1023).astype(np.uint64)
    code = np.zeros(len(points), np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return code


class _Geometry:
    """The scene's triangles reordered into chunks for culling, as arrays to upload.

    Faces are grouped by (moving object or static, closed solid or not, larger than ``BIG_FACE_M``
    or not); static small faces are chunked object by object (:func:`_object_chunks`), the others
    every ``CHUNK_FACES`` faces. A chunk has the bounding sphere of its faces and the enclosing
    sphere of its objects (a moving object's in its local frame). A *closed* object is watertight with outward
    winding: seen from outside it, only its front faces can show, so its back faces may be culled.

    ``indexed`` rows are ``position, id, mover`` per vertex and ``indices`` 3 per face; ``corners``,
    ``texels`` and ``texture_info`` (RGB; empty without) are per face corner and per texture
    (:func:`_corner_arrays`); ``chunks`` rows are ``first face, end face,
    centre xyz, radius, mover, closed, solid centre xyz, solid radius``.
    """

    def __init__(self, scene: Scene, rgb: bool) -> None:
        moving = scene.moving_objects
        objects = [o for o in scene.static_objects if len(o.mesh.faces)] + [o for o in moving if len(o.mesh.faces)]
        movers = {id(o): k for k, o in enumerate(moving)}
        mover_of = np.array([movers.get(id(o), -1) for o in objects], np.int64)
        meshes = [o.mesh for o in objects]
        spheres = np.array([_sphere_row(np.asarray(m.vertices, np.float64)) for m in meshes]).reshape(-1, 4)
        closed = np.array([_is_closed(m) for m in meshes], bool)
        vcounts = [len(m.vertices) for m in meshes]
        vstarts = np.cumsum([0] + vcounts)
        fcounts = np.array([len(m.faces) for m in meshes], np.int64)
        positions = np.concatenate([np.zeros((0, 3))] + [np.asarray(m.vertices, np.float64) for m in meshes])
        faces = np.concatenate([np.zeros((0, 3), np.int64)] + [m.faces + s for m, s in zip(meshes, vstarts)])
        face_object = np.repeat(np.arange(len(objects)), fcounts)
        self.indexed = np.zeros((len(positions), 5), np.float32)
        self.indexed[:, :3] = positions
        self.indexed[:, 3] = np.repeat([o.object_id for o in objects], vcounts)
        self.indexed[:, 4] = np.repeat(mover_of, vcounts)
        corners = positions[faces]                                     # (F, 3, 3)
        low, high = corners.min(axis=1), corners.max(axis=1)
        face_mover = mover_of[face_object]
        face_closed = closed[face_object]
        big = np.linalg.norm(high - low, axis=1) > 2 * BIG_FACE_M
        parts = []
        for is_closed in (False, True):
            static = (face_mover < 0) & (face_closed == is_closed)
            parts += _split(np.flatnonzero(static & big))
            small = np.flatnonzero(static & ~big)
            if len(small):
                parts += _object_chunks(small, face_object[small], 0.5 * (low[small] + high[small]))
        for k in range(len(moving)):
            parts += _split(np.flatnonzero(face_mover == k))
        order, chunks = [], []
        start = 0
        for part in parts:
            if not len(part):
                continue
            centre, radius = _sphere(corners[part].reshape(-1, 3))
            solid = _enclosing(spheres[np.unique(face_object[part])])
            chunks.append((start, start + len(part), *centre, radius, float(face_mover[part[0]]),
                           float(face_closed[part[0]]), *solid))
            order.append(part)
            start += len(part)
        self.order = np.concatenate(order) if order else np.zeros(0, np.int64)
        self.indices = np.ascontiguousarray(faces[self.order], np.uint32).ravel()
        self.chunks = np.array(chunks, np.float64).reshape(-1, 12)
        self.corners = np.zeros((0, 14), np.float32)
        self.texels = np.zeros((0, 4), np.uint8)
        self.texture_info: list[tuple[int, int, int]] = []
        if rgb:
            corners, self.texels, self.texture_info = _corner_arrays(objects, movers, meshes)
            self.corners = np.ascontiguousarray(corners.reshape(-1, 3, 14)[self.order].reshape(-1, 14))


def _split(faces: np.ndarray) -> list[np.ndarray]:
    """``faces`` in chunks of ``CHUNK_FACES``."""
    return [faces[first:first + CHUNK_FACES] for first in range(0, len(faces), CHUNK_FACES)]


def _object_chunks(faces: np.ndarray, owner: np.ndarray, centroids: np.ndarray) -> list[np.ndarray]:
    """Chunks of ``faces`` that keep objects together (tight bounding spheres): objects in Morton order
    of their centres, each object's faces in Morton order; an object of half a chunk or more gets
    chunks of its own, smaller ones share chunks with their neighbours in that order."""
    code = _morton(centroids)
    objects, inverse = np.unique(owner, return_inverse=True)
    centres: np.ndarray = np.stack([np.bincount(inverse, weights=centroids[:, k]) for k in range(3)], axis=1)
    centres /= np.bincount(inverse)[:, None]
    rank = np.argsort(np.argsort(_morton(centres), kind="stable"), kind="stable")
    ordered = faces[np.lexsort((code, rank[inverse]))]
    bounds = np.flatnonzero(np.diff(rank[inverse][np.lexsort((code, rank[inverse]))])) + 1
    out: list[np.ndarray] = []
    current: list[np.ndarray] = []
    for group in np.split(ordered, bounds):
        if len(group) >= CHUNK_FACES // 2:
            out += _split(group)
        else:
            if sum(len(g) for g in current) + len(group) > CHUNK_FACES:
                out.append(np.concatenate(current))
                current = []
            current.append(group)
    if current:
        out.append(np.concatenate(current))
    return out


def _sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """A bounding sphere ``(centre, radius)`` of points: the box's centre, the farthest point."""
    centre = 0.5 * (points.min(axis=0) + points.max(axis=0))
    return centre, float(np.linalg.norm(points - centre, axis=1).max())


def _sphere_row(points: np.ndarray) -> np.ndarray:
    centre, radius = _sphere(points)
    return np.array([*centre, radius])


def _enclosing(spheres: np.ndarray) -> np.ndarray:
    """A sphere ``[x, y, z, r]`` enclosing every sphere row of ``spheres``."""
    centre = 0.5 * ((spheres[:, :3] - spheres[:, 3:]).min(axis=0) + (spheres[:, :3] + spheres[:, 3:]).max(axis=0))
    return np.array([*centre, float((np.linalg.norm(spheres[:, :3] - centre, axis=1) + spheres[:, 3]).max())])


def _is_closed(mesh: trimesh.Trimesh) -> bool:
    """Whether a mesh bounds a solid with outward-wound faces (its back faces never show from outside)."""
    try:
        return bool(mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0)
    except Exception:   # degenerate meshes: draw both sides
        return False


def _corner_arrays(objects: list, movers: dict,
                   meshes: list) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int, int]]]:
    """Per triangle corner: ``position 3, id, mover, uv 2, colour 3, normal 3, texture`` (float32, 14),
    the texels of every texture ``(k, 4)`` uint8 and ``(first texel, width, height)`` per texture."""
    from visfly_dist.scene_worker.shading import SurfaceShader

    shader = SurfaceShader(meshes)
    total = int(shader.offsets[-1])
    out = np.zeros((total, 3, 14), np.float32)
    out[:, :, 0:3] = shader.vertices[shader.face_vertices]
    for o, start, stop in zip(objects, shader.offsets[:-1], shader.offsets[1:]):
        out[start:stop, :, 3] = o.object_id
        out[start:stop, :, 4] = movers.get(id(o), -1)
    out[:, :, 7:10] = shader.corner_rgb
    out[:, :, 10:13] = shader.normals[:, None, :]
    out[:, :, 13] = -1.0
    texels, info, first = [], [], 0
    for k, (start, stop, uv, image, factor) in enumerate(shader._textures):
        out[start:stop, :, 5:7] = uv
        out[start:stop, :, 7:10] = factor
        out[start:stop, :, 13] = k
        h, w = image.shape[:2]
        rgba = np.full((h, w, 4), 255, np.uint8)
        rgba[..., :3] = np.clip(np.round(image), 0, 255)
        texels.append(rgba.reshape(-1, 4))
        info.append((first, w, h))
        first += h * w
    texels_all = np.concatenate(texels) if texels else np.zeros((1, 4), np.uint8)
    return out.reshape(-1, 14), texels_all, info


class BatchEglRenderer(Renderer):
    """OpenGL renderer drawing all cameras of a call in one pass per camera (module docstring)."""

    name = "egl"

    def __init__(self, scene: Scene, cameras: Sequence[CameraSpec], drone_radius: float = 0.1,
                 lanes: int | None = None) -> None:
        super().__init__(scene, cameras, drone_radius)
        if lanes is not None and (isinstance(lanes, bool) or not isinstance(lanes, int) or not 1 <= lanes <= 64):
            raise ConfigError(f"lanes={lanes!r} must be an int in [1, 64]")
        self._lanes_asked = lanes
        self._states: dict[int, dict] = {}          # thread id -> that lane's GL objects (its context current there)
        self._lanes: list[ThreadPoolExecutor] = []   # lanes 1.. this renderer has drawn in (drawing_lanes' threads)
        self._translations = np.zeros((len(self.moving), 3))
        self._moved = 0                              # placement version; each lane uploads it once
        self._max_side = MAX_ATLAS
        self._indirect = False

    @property
    def _gl(self) -> dict | None:
        """The GL objects of the calling thread's lane."""
        return self._states.get(threading.get_ident())

    @_gl.setter
    def _gl(self, state: dict | None) -> None:
        if state is None:
            self._states.pop(threading.get_ident(), None)
        else:
            self._states[threading.get_ident()] = state

    def _built(self) -> dict:
        """The GL objects of the calling thread's lane, which :meth:`_render_rows` built before drawing."""
        s = self._gl
        assert s is not None, "drawn in a lane before its GL objects were built"
        return s

    @property
    def lanes(self) -> int:
        """Contexts drawing one call's cameras at once, each on its own thread: the ``lanes``
        argument, else ``VISFLY_EGL_LANES``, else one per core this process may use (at most
        ``MAX_DEFAULT_LANES``) on a CPU rasteriser and 1 on a GPU. With llvmpipe a context's
        vertex and triangle set-up runs on its drawing thread only (module docstring); on the 2-core
        machine of BENCHMARKS.md two lanes took a 100-camera 64x64 depth call from 40 to 29 ms for 4% more CPU."""
        if self._lanes_asked is not None:
            return self._lanes_asked
        value = os.environ.get("VISFLY_EGL_LANES", "").strip()
        if value:
            if not value.isdigit() or int(value) < 1:
                raise ConfigError(f"VISFLY_EGL_LANES={value!r} must be an int >= 1")
            return int(value)
        return 1 if gl_device().is_gpu else min(MAX_DEFAULT_LANES, usable_cores())

    def _move(self, translations: np.ndarray) -> None:
        self._translations = np.asarray(translations, np.float64)
        self._moved += 1

    # -- set-up --------------------------------------------------------------------------------

    def _build(self) -> dict:
        GL = _gl()
        kinds = sorted({c.kind for c in self.cameras}, key=KINDS.index)
        version = GL.glGetIntegerv(GL.GL_MAJOR_VERSION) * 10 + GL.glGetIntegerv(GL.GL_MINOR_VERSION)
        self._indirect = version >= 43 and os.environ.get("VISFLY_EGL_CULL", "1") != "0"
        s: dict = {"programs": {}, "targets": {}, "fbo": GL.glGenFramebuffers(1), "depth": None, "size": (0, 0),
                   "vaos": [], "buffers": [], "moved": -1}
        self._max_side = int(min(MAX_ATLAS, GL.glGetIntegerv(GL.GL_MAX_RENDERBUFFER_SIZE),
                                 *np.ravel(GL.glGetIntegerv(GL.GL_MAX_VIEWPORT_DIMS))))
        for kind in kinds:
            program = _link(KINDS.index(kind))
            s["programs"][kind] = (program, {name: GL.glGetUniformLocation(program, name) for name in (
                "movers", "drones", "proj", "tile_scale", "texels", "texture_info",
                "light", "ambient", "drone_rgb")})
        geometry = _Geometry(self.scene, "rgb" in kinds)
        s["chunks"] = geometry.chunks
        s["faces"] = len(geometry.indices) // 3
        for name, fmt in (("movers", GL.GL_RGBA32F), ("texels", GL.GL_RGBA8), ("texture_info", GL.GL_RGBA32I)):
            s[name] = _Buffer(GL.GL_TEXTURE_BUFFER, fmt)
        s["tiles"] = _Buffer(GL.GL_ARRAY_BUFFER)          # scene: per tile (instance) its view rows and place
        s["instances"] = _Buffer(GL.GL_ARRAY_BUFFER)      # drones: per (tile, drone) centre, id, the tile's rows
        s["commands"] = _Buffer(GL.GL_DRAW_INDIRECT_BUFFER)
        s["movers"].upload(np.zeros((max(len(self.moving), 1), 4), np.float32))
        s["tiles"].upload(np.zeros((1, _TILE_TEXELS, 4), np.float32))
        if {"depth", "segmentation"} & set(kinds):
            s["vao"] = self._vao(geometry.indexed, geometry.indices, 20, ((0, 3, 0), (1, 1, 3), (2, 1, 4)), s)
        if "rgb" in kinds:
            s["corner_vao"] = self._vao(geometry.corners, None, 56, (
                (0, 3, 0), (1, 1, 3), (2, 1, 4), (5, 2, 5), (6, 3, 7), (7, 3, 10), (8, 1, 13)), s)
            s["texels"].upload(geometry.texels)
            s["texture_info"].upload(np.array([(*i, 0) for i in geometry.texture_info] or [(0, 1, 1, 0)], np.int32))
        sphere = trimesh.creation.icosphere(subdivisions=DRONE_SUBDIVISIONS, radius=max(self.drone_radius, 1e-6))
        s["drone"] = self._vao(sphere.vertices, sphere.faces.ravel(), 12, ((0, 3, 0),), s, instances=s["instances"])
        s["drone_count"] = int(sphere.faces.size)
        GL.glBindVertexArray(0)
        return s

    def _vao(self, vertices: np.ndarray, indices: np.ndarray | None, stride: int, attributes: tuple, s: dict,
             instances: _Buffer | None = None) -> int:
        """A vertex array of ``vertices`` (float32 rows) and ``indices``; per-instance data from
        ``instances`` (drones: centre, id, tile) or, without it, the tile of each instance."""
        GL = _gl()
        vao = GL.glGenVertexArrays(1)
        GL.glBindVertexArray(vao)
        data = np.ascontiguousarray(vertices, np.float32)
        vbo = GL.glGenBuffers(1)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, vbo)
        GL.glBufferData(GL.GL_ARRAY_BUFFER, max(data.nbytes, 16), data if data.nbytes else None, GL.GL_STATIC_DRAW)
        s["buffers"].append(vbo)
        for location, size, offset in attributes:
            _attribute(location, size, stride, 4 * offset)
        if indices is not None:
            ebo = GL.glGenBuffers(1)
            index_data = np.ascontiguousarray(indices, np.uint32)
            GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, ebo)
            GL.glBufferData(GL.GL_ELEMENT_ARRAY_BUFFER, max(index_data.nbytes, 16),
                            index_data if index_data.nbytes else None, GL.GL_STATIC_DRAW)
            s["buffers"].append(ebo)
        if instances is not None:
            instances.upload(np.zeros((1, 20), np.float32))
            GL.glBindBuffer(GL.GL_ARRAY_BUFFER, instances.buffer)
            _attribute(3, 3, 80, 0, divisor=1)
            _attribute(1, 1, 80, 12, divisor=1)
            _tile_attributes(16, 80)
        else:
            GL.glBindBuffer(GL.GL_ARRAY_BUFFER, s["tiles"].buffer)
            _tile_attributes(0, 64)
        GL.glBindVertexArray(0)
        s["vaos"].append(vao)
        return vao

    def _release(self) -> None:
        for lane in self._lanes:
            lane.submit(self._release_lane).result()
        self._lanes = []
        leftover = list(self._states.values())     # lane 0's, made on whichever thread rendered first
        self._states.clear()
        if leftover:
            gl_context()
            for state in leftover:
                self._gl = state
                self._release_lane()

    def _release_lane(self) -> None:
        """Free this renderer's GL objects in the calling thread's lane (the context stays)."""
        GL = _gl()
        s, self._gl = self._gl, None
        if s is None:
            return
        for program, _ in s["programs"].values():
            GL.glDeleteProgram(program)
        for name in ("tiles", "movers", "texels", "texture_info", "instances", "commands"):
            s[name].delete()
        GL.glDeleteVertexArrays(len(s["vaos"]), s["vaos"])
        GL.glDeleteBuffers(len(s["buffers"]), s["buffers"])
        self._free_targets(s)
        GL.glDeleteFramebuffers(1, [s["fbo"]])

    def _free_targets(self, s: dict) -> None:
        GL = _gl()
        buffers = list(s["targets"].values()) + ([s["depth"]] if s["depth"] else [])
        if buffers:
            GL.glDeleteRenderbuffers(len(buffers), buffers)
        s["targets"], s["depth"], s["size"] = {}, None, (0, 0)

    def _atlas(self, width: int, height: int) -> None:
        """Make the atlas at least ``width x height`` (grown in steps; one attachment per kind in use)."""
        GL = _gl()
        s = self._built()
        have_w, have_h = s["size"]
        if width <= have_w and height <= have_h:
            return
        w = min(self._max_side, max(width, have_w, -(-width // 256) * 256))
        h = min(self._max_side, max(height, have_h, -(-height // 256) * 256))
        kinds = list(s["programs"])
        self._free_targets(s)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, s["fbo"])
        names = [int(x) for x in np.atleast_1d(GL.glGenRenderbuffers(len(kinds) + 1))]
        for name, kind in zip(names, kinds):
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, name)
            GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, getattr(GL, _FORMATS[kind][0]), w, h)
            GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0 + KINDS.index(kind),
                                         GL.GL_RENDERBUFFER, name)
            s["targets"][kind] = name
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, names[-1])
        GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_DEPTH_COMPONENT32F, w, h)
        GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, GL.GL_RENDERBUFFER, names[-1])
        s["depth"] = names[-1]
        status = GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER)
        if status != GL.GL_FRAMEBUFFER_COMPLETE:
            raise ConfigError(f"the egl atlas framebuffer {w}x{h} is incomplete (status 0x{int(status):x})")
        s["size"] = (w, h)

    # -- rendering -----------------------------------------------------------------------------

    def render_into(self, poses: np.ndarray, show_drones: bool, time: float,
                    out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """:meth:`render` with the images read back straight into ``out[camera.name]`` ``(n, C, H, W)``
        (e.g. rows of a shared-memory segment); returns ``out``."""
        poses = self._checked_poses(poses, show_drones)
        for cam in self.cameras:
            image = out[cam.name]
            if image.shape != (len(poses), *cam.shape) or image.dtype != np.dtype(cam.dtype):
                raise ConfigError(f"out[{cam.name!r}] is {image.dtype} {image.shape}; camera {cam.name!r} of "
                                  f"{len(poses)} drones needs {np.dtype(cam.dtype)} {(len(poses), *cam.shape)}")
        if len(poses):
            self.place(time)
            self._render_into(poses, bool(show_drones), out)
        return out

    def _render(self, poses: np.ndarray, show_drones: bool) -> dict[str, np.ndarray]:
        n = len(poses)
        out = {c.name: np.empty((n, *c.shape), c.dtype) for c in self.cameras}
        self._render_into(poses, show_drones, out)
        return out

    def _render_into(self, poses: np.ndarray, show_drones: bool, out: dict[str, np.ndarray]) -> None:
        """Render every camera of ``poses`` into ``out[camera.name]`` ``(n, C, H, W)``: the drones split
        between the lanes (:attr:`lanes`), each lane on its own thread and context."""
        lanes = min(self.lanes, max(1, len(poses) // MIN_TILES_PER_LANE))
        extra = [lane for _, lane in drawing_lanes(lanes - 1)]
        self._lanes += extra[len(self._lanes):]
        bounds = np.linspace(0, len(poses), lanes + 1).round().astype(int)
        jobs = [lane.submit(self._render_rows, poses, show_drones, out, int(lo), int(hi))
                for lane, lo, hi in zip(extra, bounds[1:-1], bounds[2:])]
        try:
            gl_context()
            self._render_rows(poses, show_drones, out, 0, int(bounds[1]))
        finally:
            for job in jobs:
                job.result()

    def _render_rows(self, poses: np.ndarray, show_drones: bool, out: dict[str, np.ndarray], lo: int, hi: int) -> None:
        """Render the cameras of drones ``lo:hi`` (seeing every drone of ``poses``) in this thread's lane."""
        GL = _gl()
        s = self._gl
        if s is None:
            s = self._gl = self._build()
        if s["moved"] != self._moved and len(self.moving):
            s["movers"].upload(np.concatenate([self._translations, np.zeros((len(self.moving), 1))], axis=1)
                               .astype(np.float32))
            s["moved"] = self._moved
        drones = show_drones and len(poses) > 1 and self.drone_radius > 0
        everyone, poses, n = poses, poses[lo:hi], hi - lo
        out = {name: image[lo:hi] for name, image in out.items()}
        views: list[np.ndarray] = []
        visible: list[np.ndarray] | None = [] if self._indirect else None    # per camera: its chunks in view
        drone_rows: list[np.ndarray | None] = []
        for cam in self.cameras:
            if cam.width > self._max_side or cam.height > self._max_side:
                raise ConfigError(f"camera {cam.name!r} is {cam.width}x{cam.height}, larger than the egl atlas "
                                  f"({self._max_side} pixels a side)")
            origins, rots = camera_world_poses(poses, cam)
            gl_rot = rots @ CAMERA_TO_GL                              # GL eye axes in the world
            view = np.zeros((n, _TILE_TEXELS, 4), np.float32)
            view[:, :3, :3] = np.swapaxes(gl_rot, 1, 2)               # world -> eye rotation
            view[:, :3, 3] = -np.einsum("aji,aj->ai", gl_rot, origins)
            views.append(view)
            if visible is not None:
                visible.append(self._chunks_in_view(cam, origins, rots))
            drone_rows.append(self._drone_instances(cam, lo, everyone, origins, rots) if drones else None)
        # Columns of tiles (camera, first agent, count), left to right; a new pass when the atlas is full.
        passes: list[list[tuple[int, int, int, int]]] = []
        current: list[tuple[int, int, int, int]] = []
        x = 0
        for c, cam in enumerate(self.cameras):    # about square: float32 interpolation is finer near the origin
            per_column = max(1, min(n, self._max_side // cam.height, int(np.ceil(np.sqrt(n * cam.width / cam.height)))))
            for a in range(0, n, per_column):
                if x + cam.width > self._max_side and current:
                    passes.append(current)
                    current, x = [], 0
                current.append((c, a, min(per_column, n - a), x))
                x += cam.width
        passes.append(current)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, s["fbo"])
        for columns in passes:
            self._draw_pass(columns, views, visible, drone_rows, out)
        GL.glBindVertexArray(0)

    def _chunks_in_view(self, cam: CameraSpec, origins: np.ndarray, rots: np.ndarray) -> np.ndarray:
        """Per camera ``a`` and chunk ``k`` ``(n, K)`` int8: 0 out of view (bounding sphere against the
        frustum), 1 in view, 2 in view and one-sided (a closed solid whose enclosing sphere is clear
        of the camera's near rectangle: every pixel's ray starts outside the solid, so it can only
        meet a front face first)."""
        chunks = self._built()["chunks"]
        centres, solids = chunks[:, 2:5].copy(), chunks[:, 8:11].copy()
        movers = chunks[:, 6].astype(np.int64)
        if len(self.moving):
            shift = self._translations[movers[movers >= 0]]
            centres[movers >= 0] += shift
            solids[movers >= 0] += shift
        local = (centres[None, :, :] - origins[:, None, :]) @ rots        # (n, K, 3) in the camera frames
        seen = spheres_in_view(cam, local, chunks[:, 5]).astype(np.int8)
        reach = cam.near * np.sqrt(1.0 + (0.5 * cam.width / cam.focal_px) ** 2 + (0.5 * cam.height / cam.focal_px) ** 2)
        away = solids[None, :, :] - origins[:, None, :]
        clear = np.einsum("aki,aki->ak", away, away) > (chunks[:, 11] + reach + 1e-6) ** 2
        return seen + (seen.astype(bool) & clear & (chunks[:, 7] > 0))

    def _drone_instances(self, cam: CameraSpec, lo: int, poses: np.ndarray, origins: np.ndarray,
                         rots: np.ndarray) -> np.ndarray:
        """Rows ``[centre xyz, segmentation id, agent - lo]`` of every (agent, other drone in its view)
        pair; the agents are drones ``lo:lo + len(origins)`` of ``poses`` (every drone of the call)."""
        centres = poses[:, :3]
        local = (centres[None, :, :] - origins[:, None, :]) @ rots
        own = np.arange(len(origins))[:, None] + lo == np.arange(len(poses))[None, :]
        visible = spheres_in_view(cam, local, self.drone_radius) & ~own
        agent, other = np.nonzero(visible)
        rows = np.empty((len(agent), 5), np.float32)
        rows[:, :3] = centres[other]
        rows[:, 3] = drone_segmentation_id(other)
        rows[:, 4] = agent
        return rows

    def _draw_pass(self, columns: list[tuple[int, int, int, int]], views: list[np.ndarray],
                   visible: list[np.ndarray] | None, drone_rows: list[np.ndarray | None],
                   out: dict[str, np.ndarray]) -> None:
        """Draw one atlas of columns ``(camera, first agent, count, x)`` and read each column back."""
        GL = _gl()
        s = self._built()
        width = sum(self.cameras[c].width for c, _, _, _ in columns)
        height = max(self.cameras[c].height * count for c, _, count, _ in columns)
        self._atlas(width, height)
        atlas_w, atlas_h = s["size"]
        # The pass's tiles in column order: view rows and the place of each tile in the atlas.
        blocks = []
        for c, a, count, x0 in columns:
            cam = self.cameras[c]
            block = views[c][a:a + count].copy()
            block[:, 3, 0] = (2.0 * x0 + cam.width) / atlas_w - 1.0
            block[:, 3, 1] = (2.0 * np.arange(count) * cam.height + cam.height) / atlas_h - 1.0
            blocks.append(block)
        tiles = np.concatenate(blocks)
        # Cameras of the pass: their columns are consecutive, so their tiles and agents are too.
        groups, tile = [], 0
        for c in dict.fromkeys(c for c, _, _, _ in columns):
            mine = [col for col in columns if col[0] == c]
            count = sum(col[2] for col in mine)
            groups.append((c, mine, tile, mine[0][1], count))
            tile += count
        draws = self._commands(groups, tiles, visible) if visible is not None else None
        if draws is None:
            s["tiles"].upload(tiles)
        GL.glViewport(0, 0, atlas_w, atlas_h)
        GL.glDisable(GL.GL_CULL_FACE)
        GL.glDisable(GL.GL_BLEND)
        GL.glDisable(GL.GL_MULTISAMPLE)
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthMask(GL.GL_TRUE)
        GL.glDepthFunc(GL.GL_LESS)
        for k in range(4):
            GL.glEnable(GL.GL_CLIP_DISTANCE0 + k)
        GL.glEnable(GL.GL_SCISSOR_TEST)
        GL.glScissor(0, 0, width, height)
        GL.glClear(GL.GL_DEPTH_BUFFER_BIT)
        for k, (c, mine, first, agent0, count) in enumerate(groups):
            cam = self.cameras[c]
            slot = KINDS.index(cam.kind)
            GL.glDrawBuffers(slot + 1, [GL.GL_NONE] * slot + [GL.GL_COLOR_ATTACHMENT0 + slot])
            x0, x1 = mine[0][3], mine[-1][3] + cam.width
            GL.glScissor(x0, 0, x1 - x0, cam.height * max(col[2] for col in mine))   # draws stay in it too
            if cam.kind == "depth":
                GL.glClearBufferfv(GL.GL_COLOR, slot, np.array([cam.far, 0, 0, 0], np.float32))
            elif cam.kind == "segmentation":
                GL.glClearBufferuiv(GL.GL_COLOR, slot, np.zeros(4, np.uint32))
            else:
                GL.glClearBufferfv(GL.GL_COLOR, slot, np.array([*(np.asarray(SKY_RGB) / 255.0), 1.0], np.float32))
            rows = drone_rows[c]
            if rows is not None:   # centre, id, then the rows of the seeing agent's tile
                rows = rows[(rows[:, 4] >= agent0) & (rows[:, 4] < agent0 + count)]
                seer = rows[:, 4].astype(np.int64) + first - agent0
                rows = np.concatenate([rows[:, :4], tiles[seer].reshape(-1, 16)], axis=1)
            self._draw_camera(cam, first, count, atlas_w, atlas_h, rows, None if draws is None else draws[k])
        GL.glDisable(GL.GL_SCISSOR_TEST)
        for k in range(4):
            GL.glDisable(GL.GL_CLIP_DISTANCE0 + k)
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
        for c, a, count, x0 in columns:
            cam = self.cameras[c]
            _, read_format, read_type, _ = _FORMATS[cam.kind]
            fmt, kind = getattr(GL, read_format), getattr(GL, read_type)
            GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0 + KINDS.index(cam.kind))
            dest = out[cam.name][a:a + count]
            if cam.kind == "rgb":
                staging = np.empty((count, cam.height, cam.width, 3), np.uint8)
                _read(x0, cam.width, cam.height * count, fmt, kind, staging)
                dest[...] = staging.transpose(0, 3, 1, 2)
            elif dest.flags.c_contiguous:
                _read(x0, cam.width, cam.height * count, fmt, kind, dest)
            else:
                staging = np.empty(dest.shape, dest.dtype)
                _read(x0, cam.width, cam.height * count, fmt, kind, staging)
                dest[...] = staging

    def _commands(self, groups: list, tiles: np.ndarray, visible: list[np.ndarray]) -> list[tuple]:
        """Upload the indirect draws of every camera of the pass: one per chunk in view of any of its
        tiles, instanced over those tiles (the instances' attributes are the tiles' rows, copied per
        (chunk, tile) pair), apart for two-sided and one-sided (back faces culled) chunks. Per camera
        ``((byte offset, draws) two-sided, (byte offset, draws) one-sided)`` in the command buffer."""
        s = self._built()
        chunks = s["chunks"]
        parts, pairs, spans, total, instances = [], [], [], 0, 0
        for c, _, first, agent0, count in groups:
            seen = visible[c][agent0:agent0 + count].T                    # (K, tiles of this camera)
            rgb = self.cameras[c].kind == "rgb"
            spans_c = []
            for code in (1, 2):
                chunk, tile = np.nonzero(seen == code)                    # sorted by chunk
                used, per_chunk = np.unique(chunk, return_counts=True)
                rows = np.zeros((len(used), 4 if rgb else 5), np.uint32)
                rows[:, 0] = 3 * (chunks[used, 1] - chunks[used, 0])
                rows[:, 1] = per_chunk
                rows[:, 2] = 3 * chunks[used, 0]
                rows[:, -1] = instances + np.cumsum(per_chunk) - per_chunk   # base instance: its first pair
                pairs.append(tiles[first + tile])
                instances += len(tile)
                parts.append(rows.view(np.uint8).ravel())
                spans_c.append((total, len(rows)))
                total += rows.nbytes
            spans.append(tuple(spans_c))
        s["commands"].upload(np.concatenate(parts))
        s["tiles"].upload(np.concatenate(pairs))
        return spans

    def _draw_camera(self, cam: CameraSpec, first: int, count: int, atlas_w: int, atlas_h: int,
                     drone_rows: np.ndarray | None, commands: tuple | None) -> None:
        """Draw the scene and the drones seen into one camera's ``count`` tiles of the pass (first
        tile ``first``): indirect draws of the chunks in view, or (no culling) everything instanced."""
        GL = _gl()
        s = self._built()
        program, u = s["programs"][cam.kind]
        GL.glUseProgram(program)
        f, near, far = cam.focal_px, cam.near, cam.far
        GL.glUniform4f(u["proj"], 2.0 * f / cam.width, 2.0 * f / cam.height,
                       -(far + near) / (far - near), -2.0 * far * near / (far - near))
        GL.glUniform2f(u["tile_scale"], cam.width / atlas_w, cam.height / atlas_h)
        _bind_texture(1, s["movers"].texture, u["movers"])
        rgb = cam.kind == "rgb"
        if rgb:
            _bind_texture(2, s["texels"].texture, u["texels"])
            _bind_texture(3, s["texture_info"].texture, u["texture_info"])
            GL.glUniform3f(u["light"], *LIGHT_DIRECTION)
            GL.glUniform1f(u["ambient"], AMBIENT)
            GL.glUniform3f(u["drone_rgb"], *(float(v) for v in DRONE_RGB))
        GL.glUniform1i(u["drones"], 0)
        GL.glVertexAttrib3f(3, 0.0, 0.0, 0.0)   # the scene has no instance offset
        if s["faces"]:
            GL.glBindVertexArray(s["corner_vao"] if rgb else s["vao"])
            GL.glBindBuffer(GL.GL_ARRAY_BUFFER, s["tiles"].buffer)
            if commands is not None:      # per chunk in view, instanced over the tiles that see it
                _tile_attributes(0, 64)
                GL.glBindBuffer(GL.GL_DRAW_INDIRECT_BUFFER, s["commands"].buffer)
                for (offset, draws), one_sided in zip(commands, (False, True)):
                    if one_sided:   # outward faces are counter-clockwise, clockwise on the flipped tiles
                        GL.glEnable(GL.GL_CULL_FACE)
                        GL.glFrontFace(GL.GL_CW)
                        GL.glCullFace(GL.GL_BACK)
                    if draws and rgb:
                        GL.glMultiDrawArraysIndirect(GL.GL_TRIANGLES, ctypes.c_void_p(offset), draws, 0)
                    elif draws:
                        GL.glMultiDrawElementsIndirect(GL.GL_TRIANGLES, GL.GL_UNSIGNED_INT, ctypes.c_void_p(offset),
                                                       draws, 0)
                GL.glDisable(GL.GL_CULL_FACE)
            else:                         # every tile draws everything; instance k: tile first + k
                _tile_attributes(64 * first, 64)
                if rgb:
                    GL.glDrawArraysInstanced(GL.GL_TRIANGLES, 0, 3 * s["faces"], count)
                else:
                    GL.glDrawElementsInstanced(GL.GL_TRIANGLES, 3 * s["faces"], GL.GL_UNSIGNED_INT,
                                               ctypes.c_void_p(0), count)
        if drone_rows is None or not len(drone_rows):
            return
        GL.glVertexAttrib1f(2, -1.0)              # drones do not move with an obstacle
        s["instances"].upload(drone_rows)
        GL.glBindVertexArray(s["drone"])
        GL.glUniform1i(u["drones"], 1)
        GL.glDrawElementsInstanced(GL.GL_TRIANGLES, s["drone_count"], GL.GL_UNSIGNED_INT, ctypes.c_void_p(0),
                                   len(drone_rows))


def _attribute(location: int, size: int, stride: int, offset: int, divisor: int = 0) -> None:
    GL = _gl()
    GL.glEnableVertexAttribArray(location)
    GL.glVertexAttribPointer(location, size, GL.GL_FLOAT, GL.GL_FALSE, stride, ctypes.c_void_p(offset))
    if divisor:
        GL.glVertexAttribDivisor(location, divisor)


def _tile_attributes(offset: int, stride: int) -> None:
    """Per-instance attributes 4, 9, 10, 11: a tile's three world -> eye rows and its place, at ``offset``."""
    for k, location in enumerate((4, 9, 10, 11)):
        _attribute(location, 4, stride, offset + 16 * k, divisor=1)


def _bind_texture(unit: int, texture: int, location: int) -> None:
    GL = _gl()
    GL.glActiveTexture(GL.GL_TEXTURE0 + unit)
    GL.glBindTexture(GL.GL_TEXTURE_BUFFER, texture)
    GL.glUniform1i(location, unit)


def _read(x: int, width: int, height: int, fmt: int, kind: int, dest: np.ndarray) -> None:
    """``glReadPixels`` of the atlas rectangle ``[x, x + width) x [0, height)`` into ``dest`` (C-contiguous)."""
    from OpenGL.raw.GL.VERSION.GL_1_0 import glReadPixels

    glReadPixels(x, 0, width, height, fmt, kind, ctypes.c_void_p(dest.ctypes.data))


def _link(kind: int) -> int:
    GL = _gl()
    program = GL.glCreateProgram()
    shaders = []
    for stage, source in ((GL.GL_VERTEX_SHADER, VERTEX_SHADER), (GL.GL_FRAGMENT_SHADER, FRAGMENT_SHADER)):
        shader = GL.glCreateShader(stage)
        GL.glShaderSource(shader, f"#version 330 core\n#define KIND {kind}\n{source}")
        GL.glCompileShader(shader)
        if not GL.glGetShaderiv(shader, GL.GL_COMPILE_STATUS):
            raise ConfigError(f"egl shader failed to compile: {GL.glGetShaderInfoLog(shader)!r}")
        GL.glAttachShader(program, shader)
        shaders.append(shader)
    GL.glLinkProgram(program)
    if not GL.glGetProgramiv(program, GL.GL_LINK_STATUS):
        raise ConfigError(f"egl shaders failed to link: {GL.glGetProgramInfoLog(program)!r}")
    for shader in shaders:
        GL.glDeleteShader(shader)
    return program
