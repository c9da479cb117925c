"""The native packet tracer (``native/tracer.cpp``) through ctypes.

The library is built at install time (``make -C visfly_dist/scene_worker/native``, run by
``setup.sh``) against Debian's Embree 3. :func:`load_library` finds it, or says why not; the
raycast backend then falls back to embreex. ``VISFLY_NATIVE_TRACER=0`` turns it off.

A :class:`NativeScene` holds one scene's Embree BVH (built once); a :class:`NativeInstancedScene`
a scene with moving obstacles (the static BVH plus instances moved per call). :func:`trace` renders a list of
:class:`Batch` es (one camera of many drones of one scene each) in ONE native call: the tracer's
threads spread over every frame of every batch, and ctypes releases the GIL for the whole call.

A :class:`NativeMesh` (``native/queries.cpp``) answers closest-point queries: the nearest point of
a mesh to every position of a call in one native call (Embree's ``rtcPointQuery``, float64 maths).
"""

from __future__ import annotations

import ctypes
import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from visfly_dist.errors import ConfigError
from visfly_dist.native import load_native

LIBRARY_PATH = Path(__file__).parent / "native" / "libvisfly_tracer.so"
LIBRARY_VERSION = 5
DISABLE_ENV = "VISFLY_NATIVE_TRACER"

_f32p = ctypes.POINTER(ctypes.c_float)
_f64p = ctypes.POINTER(ctypes.c_double)
_i32p = ctypes.POINTER(ctypes.c_int32)


class _Batch(ctypes.Structure):
    """``struct vf_batch`` of tracer.cpp (field for field)."""

    _fields_ = [
        ("scene", ctypes.c_void_p), ("n", ctypes.c_int32), ("width", ctypes.c_int32), ("height", ctypes.c_int32),
        ("near_m", ctypes.c_double), ("far_m", ctypes.c_double),
        ("right", ctypes.c_void_p), ("down", ctypes.c_void_p), ("origins", ctypes.c_void_p), ("rots", ctypes.c_void_p),
        ("depth", ctypes.c_void_p), ("prim", ctypes.c_void_p), ("uv", ctypes.c_void_p),
        ("seg_table", ctypes.c_void_p), ("seg", ctypes.c_void_p),
        ("vis_offsets", ctypes.c_void_p), ("vis_drone", ctypes.c_void_p), ("vis_centre", ctypes.c_void_p),
        ("vis_dist2", ctypes.c_void_p), ("radius", ctypes.c_double), ("focal", ctypes.c_double),
        ("right64", ctypes.c_void_p), ("down64", ctypes.c_void_p), ("drone", ctypes.c_void_p),
        ("rots64", ctypes.c_void_p), ("light_dir", ctypes.c_void_p), ("ambient", ctypes.c_double),
        ("light", ctypes.c_void_p), ("prim_offsets", ctypes.c_void_p), ("moving", ctypes.c_void_p),
        ("moving_count", ctypes.c_int32), ("moving_centres", ctypes.c_void_p), ("moving_bounds", ctypes.c_void_p),
        ("moving_focal", ctypes.c_double),
    ]


@functools.lru_cache(maxsize=1)
def load_library() -> tuple[ctypes.CDLL | None, str]:
    """The loaded tracer library, or ``None`` and the reason it is not used."""
    return load_native(LIBRARY_PATH, "vf_version", LIBRARY_VERSION, DISABLE_ENV, "g++ and libembree-dev", _declare)


def _declare(lib: ctypes.CDLL) -> None:
    lib.vf_last_error.restype = ctypes.c_char_p
    lib.vf_scene_new.restype = ctypes.c_void_p
    lib.vf_scene_new.argtypes = [_f32p, ctypes.c_int64]
    lib.vf_scene_free.restype = None
    lib.vf_scene_free.argtypes = [ctypes.c_void_p]
    lib.vf_instanced_new.restype = ctypes.c_void_p
    lib.vf_instanced_new.argtypes = [_f32p, ctypes.POINTER(ctypes.c_int64), ctypes.c_int32]
    lib.vf_instanced_free.restype = None
    lib.vf_instanced_free.argtypes = [ctypes.c_void_p]
    lib.vf_instanced_move.restype = ctypes.c_int
    lib.vf_instanced_move.argtypes = [ctypes.c_void_p, _f32p]
    lib.vf_instanced_scene.restype = ctypes.c_void_p
    lib.vf_instanced_scene.argtypes = [ctypes.c_void_p]
    lib.vf_instanced_moving.restype = ctypes.c_void_p
    lib.vf_instanced_moving.argtypes = [ctypes.c_void_p]
    lib.vf_trace.restype = ctypes.c_int
    lib.vf_trace.argtypes = [ctypes.POINTER(_Batch), ctypes.c_int32, ctypes.c_int32]
    lib.vf_points_new.restype = ctypes.c_void_p
    lib.vf_points_new.argtypes = [_f64p, ctypes.c_int64, _i32p, ctypes.c_int64]
    lib.vf_points_free.restype = None
    lib.vf_points_free.argtypes = [ctypes.c_void_p]
    lib.vf_closest.restype = ctypes.c_int
    lib.vf_closest.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int32, ctypes.c_void_p,
                               ctypes.c_void_p]   # raw addresses: data_as() would cost more than one query
    lib.vf_closest_many.restype = ctypes.c_int
    lib.vf_closest_many.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int32,
                                    ctypes.c_void_p, ctypes.c_void_p]


def available() -> bool:
    """Whether the native tracer can be used here."""
    return load_library()[0] is not None


def _lib() -> ctypes.CDLL:
    lib, reason = load_library()
    if lib is None:
        raise ConfigError(f"the native tracer is unavailable: {reason}")
    return lib


def _error(lib: ctypes.CDLL, what: str) -> RuntimeError:
    return RuntimeError(f"native tracer: {what} failed: {lib.vf_last_error().decode(errors='replace')}")


class NativeScene:
    """One scene's triangles in an Embree BVH (robust), built on construction.

    Args:
        triangles: ``(F, 3, 3)`` vertices of every triangle (a soup); ``F`` may be 0 (nothing is hit).
    """

    def __init__(self, triangles: np.ndarray) -> None:
        self._lib = _lib()
        self.handle: int | None = None
        tris = np.ascontiguousarray(triangles, dtype=np.float32)
        if tris.ndim != 3 or tris.shape[1:] != (3, 3):
            raise ConfigError(f"triangles shape {tris.shape} must be (F, 3, 3)")
        if len(tris):
            handle = self._lib.vf_scene_new(tris.ctypes.data_as(_f32p), len(tris))
            if not handle:
                raise _error(self._lib, f"building the BVH of {len(tris)} triangles")
            self.handle = handle

    def close(self) -> None:
        """Free the BVH; idempotent."""
        if self.handle is not None:
            self._lib.vf_scene_free(self.handle)
            self.handle = None

    def __del__(self) -> None:  # last resort; renderers call close()
        self.close()


class NativeInstancedScene:
    """A scene with moving parts: Embree instances over per-part BVHs, moved by translations.

    Part 0 is the static geometry (a plain BVH, built once, as a :class:`NativeScene`'s), parts 1..
    the moving objects: instances of their local-frame BVHs (built once) in a top-level scene of
    their own (``moving``); :meth:`move` sets their translations and re-commits that top level
    only. The tracer traces the static part, then the instances. Hits report the triangle index in
    the concatenation of the parts (``prim_offsets``), as a flat scene would.

    Args:
        triangles: ``(F, 3, 3)`` every part's triangles, part after part.
        counts: ``(P,)`` triangles per part (a part may be empty).
        bounds: ``(P - 1, 2, 3)`` each moving part's axis-aligned box ``[low, high]`` in its own frame
            (tiles that no part's box can show in skip the instances).

    Attributes:
        centres: ``(P - 1, 3)`` float64 the moving parts' translations (where :meth:`move` put them).
    """

    def __init__(self, triangles: np.ndarray, counts: Sequence[int], bounds: np.ndarray) -> None:
        self._lib = _lib()
        self.handle: int | None = None
        self._instanced: int | None = None
        tris = np.ascontiguousarray(triangles, dtype=np.float32)
        counts64 = np.ascontiguousarray(counts, dtype=np.int64)
        if tris.ndim != 3 or tris.shape[1:] != (3, 3) or counts64.sum() != len(tris) or np.any(counts64 < 0):
            raise ConfigError(f"triangles shape {tris.shape} must be (F, 3, 3) with F = sum(counts) = {counts64.sum()}")
        self.parts = len(counts64)
        self.prim_offsets = np.ascontiguousarray(np.concatenate([[0], np.cumsum(counts64)[:-1]]), dtype=np.int32)
        self.bounds = np.ascontiguousarray(bounds, dtype=np.float64).reshape(-1, 2, 3)
        self.centres = np.zeros((self.parts - 1, 3))
        if self.bounds.shape != (self.parts - 1, 2, 3):
            raise ConfigError(f"bounds shape {self.bounds.shape} must be ({self.parts - 1}, 2, 3), one box per moving part")
        handle = self._lib.vf_instanced_new(tris.ctypes.data_as(_f32p), counts64.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)),
                                            self.parts)
        if not handle:
            raise _error(self._lib, f"building the instanced scene of {self.parts} parts, {len(tris)} triangles")
        self._instanced = handle
        self.handle = self._lib.vf_instanced_scene(handle)
        self.moving = self._lib.vf_instanced_moving(handle)

    def move(self, translations: np.ndarray) -> None:
        """Place the moving parts 1..P-1: ``(P - 1, 3)`` translations."""
        if self._instanced is None:
            raise ConfigError("move() on a closed NativeInstancedScene")
        t = np.ascontiguousarray(translations, dtype=np.float32)
        if t.shape != (self.parts - 1, 3):
            raise ConfigError(f"translations shape {t.shape} must be ({self.parts - 1}, 3)")
        if self._lib.vf_instanced_move(self._instanced, t.ctypes.data_as(_f32p)) != 0:
            raise _error(self._lib, "moving the instances")
        self.centres = np.ascontiguousarray(translations, dtype=np.float64)

    def close(self) -> None:
        """Free the BVHs; idempotent."""
        if self._instanced is not None:
            self._lib.vf_instanced_free(self._instanced)
            self._instanced = self.handle = self.moving = None

    def __del__(self) -> None:  # last resort; renderers call close()
        self.close()


class NativeMesh:
    """One mesh's triangles in an Embree BVH for closest-point queries, built on construction.

    Args:
        vertices: ``(V, 3)`` float64 vertex positions.
        faces: ``(F, 3)`` vertex indices of each triangle, ``F >= 1``.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        self._lib = _lib()
        self.handle: int | None = None
        verts = np.ascontiguousarray(vertices, dtype=np.float64)
        tris = np.ascontiguousarray(faces, dtype=np.int32)
        if verts.ndim != 2 or verts.shape[1] != 3:
            raise ConfigError(f"vertices shape {verts.shape} must be (V, 3)")
        if tris.ndim != 2 or tris.shape[1] != 3 or not len(tris):
            raise ConfigError(f"faces shape {tris.shape} must be (F, 3) with F >= 1")
        handle = self._lib.vf_points_new(verts.ctypes.data_as(_f64p), len(verts), tris.ctypes.data_as(_i32p), len(tris))
        if not handle:
            raise _error(self._lib, f"building the closest-point BVH of {len(tris)} triangles")
        self.handle = handle

    def closest(self, positions: np.ndarray, threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Distance ``(n,)`` to and nearest point ``(n, 3)`` on the mesh of each position, float64.

        One native call on ``threads`` threads, GIL released.
        """
        if self.handle is None:
            raise ConfigError("closest() on a closed NativeMesh")
        pos = np.ascontiguousarray(positions, dtype=np.float64)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise ConfigError(f"positions shape {pos.shape} must be (n, 3)")
        dist = np.empty(len(pos))
        nearest = np.empty((len(pos), 3))
        if len(pos) and self._lib.vf_closest(self.handle, pos.ctypes.data, len(pos), int(threads),
                                             dist.ctypes.data, nearest.ctypes.data) != 0:
            raise _error(self._lib, f"closest points of {len(pos)} positions")
        return dist, nearest

    def close(self) -> None:
        """Free the BVH; idempotent."""
        if self.handle is not None:
            self._lib.vf_points_free(self.handle)
            self.handle = None

    def __del__(self) -> None:  # last resort
        self.close()


def closest_many(meshes: Sequence[NativeMesh], group: np.ndarray, positions: np.ndarray,
                 threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`NativeMesh.closest` of row ``i`` of ``positions`` against ``meshes[group[i]]``, for
    every row in ONE native call (a worker's scenes together).

    Args:
        meshes: the meshes, each open.
        group: ``(n,)`` index into ``meshes`` of each row.
        positions: ``(n, 3)`` world positions.
    """
    lib = _lib()
    pos = np.ascontiguousarray(positions, dtype=np.float64)
    group = np.ascontiguousarray(group, dtype=np.int32)
    if pos.ndim != 2 or pos.shape[1] != 3 or group.shape != (len(pos),):
        raise ConfigError(f"positions {pos.shape} must be (n, 3) and group {group.shape} must be (n,)")
    if any(m.handle is None for m in meshes):
        raise ConfigError("closest_many() on a closed NativeMesh")
    if len(group) and (group.min() < 0 or group.max() >= len(meshes)):
        raise ConfigError(f"group indices must be in [0, {len(meshes)})")
    dist = np.empty(len(pos))
    nearest = np.empty((len(pos), 3))
    handles = (ctypes.c_void_p * max(1, len(meshes)))(*(m.handle for m in meshes))
    if len(pos) and lib.vf_closest_many(handles, group.ctypes.data, pos.ctypes.data, len(pos), int(threads),
                                        dist.ctypes.data, nearest.ctypes.data) != 0:
        raise _error(lib, f"closest points of {len(pos)} positions in {len(meshes)} meshes")
    return dist, nearest


@dataclass
class Drones:
    """The other drones one camera of a batch may see: spheres, tested in float64.

    Attributes:
        offsets: ``(n + 1,)`` int32: frame ``a`` sees entries ``offsets[a]:offsets[a + 1]``, drawn in order.
        index: ``(K,)`` int32 drone of each entry (its row in the call).
        centres: ``(K, 3)`` float64 its centre in the camera frame of the frame seeing it.
        dist2: ``(K,)`` float64 squared norm of ``centres``.
        radius: sphere radius, metres; focal: focal length, pixels.
        right, down: ``(W,)``, ``(H,)`` float64 pixel slopes.
        rots: ``(n, 3, 3)`` float64 camera-to-world rotations (for the light on the spheres).
        light_dir: ``(3,)`` float64 unit vector towards the light; ambient: its ambient share.
    """

    offsets: np.ndarray
    index: np.ndarray
    centres: np.ndarray
    dist2: np.ndarray
    radius: float
    focal: float
    right: np.ndarray
    down: np.ndarray
    rots: np.ndarray
    light_dir: np.ndarray
    ambient: float


@dataclass
class Batch:
    """One camera of ``n`` drones of one scene, with its output arrays (filled by :func:`trace`).

    Attributes:
        scene: the scene traced.
        right, down: ``(W,)``, ``(H,)`` float32 pixel slopes (``camera_math.pixel_slopes``).
        near, far: clip distances, metres.
        origins: ``(n, 3)`` float32 camera centres; ``rots``: ``(n, 3, 3)`` float32 camera-to-world.
        depth: ``(n, H, W)`` float32 output.
        prim: ``(n, H, W)`` int32 triangle hit (``-1``: none), or None.
        uv: ``(n, H, W, 2)`` float32 barycentrics of the hit, or None.
        seg_table: ``(F + 1,)`` uint16 object id of triangle ``k`` at ``k + 1``; with ``seg``.
        seg: ``(n, H, W)`` uint16 output, or None.
        drones: the other drones to draw, or None.
        drone: ``(n, H, W)`` int32 output: the drone seen (``-1``: none), or None.
        light: ``(n, H, W)`` float64 output: brightness of the drone seen, or None (needs ``drones.rots``).

    An instanced scene's batch also passes its ``prim_offsets``, its moving top-level scene and the
    moving parts' boxes (all taken from the scene): tiles no box's image covers skip the moving
    pass.
    """

    scene: "NativeScene | NativeInstancedScene"
    right: np.ndarray
    down: np.ndarray
    near: float
    far: float
    origins: np.ndarray
    rots: np.ndarray
    depth: np.ndarray
    prim: np.ndarray | None = None
    uv: np.ndarray | None = None
    seg_table: np.ndarray | None = None
    seg: np.ndarray | None = None
    drones: "Drones | None" = None
    drone: np.ndarray | None = None
    light: np.ndarray | None = None
    focal: float = 0.0

    def to_struct(self) -> _Batch:
        n, h, w = self.depth.shape
        checks = [(self.right, np.float32, (w,)), (self.down, np.float32, (h,)), (self.origins, np.float32, (n, 3)),
                  (self.rots, np.float32, (n, 3, 3)), (self.depth, np.float32, (n, h, w)),
                  (self.prim, np.int32, (n, h, w)), (self.uv, np.float32, (n, h, w, 2)),
                  (self.seg, np.uint16, (n, h, w)), (self.drone, np.int32, (n, h, w)),
                  (self.light, np.float64, (n, h, w))]
        d = self.drones
        if d is not None:
            k = len(d.index)
            checks += [(d.offsets, np.int32, (n + 1,)), (d.index, np.int32, (k,)), (d.centres, np.float64, (k, 3)),
                       (d.dist2, np.float64, (k,)), (d.right, np.float64, (w,)), (d.down, np.float64, (h,)),
                       (d.rots, np.float64, (n, 3, 3)), (d.light_dir, np.float64, (3,))]
        for a, dtype, shape in checks:  # internal invariants: a bad array here would be a memory error
            assert a is None or (a.dtype == dtype and a.shape == shape and a.flags.c_contiguous), (a, dtype, shape)
        assert self.seg is None or (self.seg_table is not None and self.seg_table.dtype == np.uint16
                                    and self.seg_table.flags.c_contiguous)
        assert (self.drone is None and self.light is None) or d is not None
        ptr = lambda a: None if a is None else a.ctypes.data  # noqa: E731
        out = _Batch(self.scene.handle, n, w, h, float(self.near), float(self.far), ptr(self.right), ptr(self.down),
                     ptr(self.origins), ptr(self.rots), ptr(self.depth), ptr(self.prim), ptr(self.uv),
                     ptr(self.seg_table), ptr(self.seg))
        if isinstance(self.scene, NativeInstancedScene):
            sc = self.scene
            assert sc.centres.dtype == np.float64 and sc.centres.shape == (sc.parts - 1, 3) and sc.centres.flags.c_contiguous
            out.prim_offsets, out.moving = ptr(sc.prim_offsets), sc.moving
            out.moving_count, out.moving_centres, out.moving_bounds = sc.parts - 1, ptr(sc.centres), ptr(sc.bounds)
            out.moving_focal = float(self.focal)
        if d is not None:
            out.vis_offsets, out.vis_drone, out.vis_centre, out.vis_dist2 = (
                ptr(d.offsets), ptr(d.index), ptr(d.centres), ptr(d.dist2))
            out.radius, out.focal, out.ambient = float(d.radius), float(d.focal), float(d.ambient)
            out.right64, out.down64, out.rots64, out.light_dir = ptr(d.right), ptr(d.down), ptr(d.rots), ptr(d.light_dir)
            out.drone, out.light = ptr(self.drone), ptr(self.light)
        return out


def trace(batches: Sequence[Batch], threads: int) -> None:
    """Fill every batch's outputs in one native call on ``threads`` threads (GIL released)."""
    lib = _lib()
    if not batches:
        return
    array = (_Batch * len(batches))(*(b.to_struct() for b in batches))
    if lib.vf_trace(array, len(batches), int(threads)) != 0:
        raise _error(lib, f"tracing {len(batches)} batches")
