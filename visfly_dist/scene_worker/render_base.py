"""The renderers' entry point: the backend choice, ``make_renderer`` and several scenes in one call.

A renderer draws every camera of every drone of one scene for a batch of poses:

    r = make_renderer("raycast", scene, cameras, drone_radius=0.1)
    images = r.render(poses)          # {camera.name: (n, C, H, W) array of camera.dtype}
    r.close()

Both backends follow :mod:`visfly_dist.scene_worker.camera_math`'s frames, read depth at pixel
centres (z-depth, ``far`` where nothing is hit or beyond ``far``, nothing nearer than ``near``),
and share the look of what has no material: the sky colour, the drones' colour and the light.

With ``show_drones=True`` the other drones of the same call are drawn as spheres of
``drone_radius`` (a camera never sees its own drone). Agent ``k`` of the call (its row in
``poses``) has segmentation id ``drone_segmentation_id(k) = 65535 - k``; scene object ids must stay
below the ids of the drones in use.

Moving obstacles are drawn where they are at the call's ``time`` (seconds of simulation time): a
renderer keeps each moving object's mesh in its local frame and only translates it per call
(:meth:`Renderer.place`), never rebuilding the static geometry.

Imports point one way: this module imports the backends (lazily, so that a backend's libraries load
only when it is used), the backends import :mod:`visfly_dist.scene_worker.render_common` (the
:class:`Renderer` base class, colours, light, segmentation ids) and
:mod:`visfly_dist.scene_worker.shading`, and none of them imports this module. The names of
``render_common`` and ``shading.face_rgb`` are re-exported here.
"""

from __future__ import annotations

import ctypes.util
import functools
import importlib.util
import logging
from typing import Any, Sequence

import numpy as np

from visfly_dist.errors import ConfigError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.scene_worker.camera_math import camera_world_poses
from visfly_dist.scene_worker.render_common import (  # noqa: F401 - re-exported: the renderers' public names
    AMBIENT,
    DRONE_RGB,
    DRONE_SEGMENTATION_MAX,
    LIGHT_DIRECTION,
    SKY_RGB,
    Renderer,
    checked_time,
    drone_segmentation_id,
)
from visfly_dist.scene_worker.shading import face_rgb  # noqa: F401 - re-exported
from visfly_dist.scenes.scene import Scene

log = logging.getLogger(__name__)

BACKENDS = ("raycast", "egl")
BACKEND_CHOICES = ("auto", *BACKENDS)
RAYCAST_MAX_PIXELS = 128 * 128
"""With the embreex tracer, ``auto`` picks ``egl`` for depth/segmentation cameras larger than this."""
NATIVE_RAYCAST_MAX_PIXELS = 256 * 256
"""With the native packet tracer, ``auto`` picks ``egl`` for cameras larger than this."""


def render_scenes(items: Sequence[tuple]) -> list[dict[str, np.ndarray]]:
    """Render several scenes at once: one result per item, as ``renderer.render(poses, show_drones, time)``.

    Raycast renderers on the native tracer are traced together in ONE native call (its threads spread
    over every camera of every scene, the GIL released once); other renderers are called in turn,
    and so is a renderer met again at another time than its first item's (it can be placed at one
    time per trace). Every item is validated before anything is rendered.

    Args:
        items: ``(renderer, poses (n, 7), show_drones)`` or ``(renderer, poses, show_drones, time)``
            per scene; ``time`` (s, default 0) places the moving obstacles, per item.

    Returns:
        ``[{camera.name: (n, C, H, W) array}]``, in the order of ``items``.
    """
    return _render_all(items, [None] * len(items))


def render_scenes_into(items: Sequence[tuple], out: dict[str, np.ndarray], starts: Sequence[int] | None = None) -> None:
    """:func:`render_scenes` with every item's images written into ``out``.

    ``out``: camera name -> ``(rows, C, H, W)`` C-contiguous array (e.g. a view of a shared-memory
    segment). Item ``i``'s images go to rows ``starts[i]`` onwards (default: the items one after
    another from row 0). The native tracer writes depth and segmentation straight into it, and so
    does the egl renderer with every image (``render_into``); other images are copied in once.
    """
    counts = [len(item[1]) for item in items]
    if starts is None:
        starts = (np.cumsum(counts) - counts).tolist() if counts else []
    outs = [{name: image[int(start):int(start) + count] for name, image in out.items()}
            for start, count in zip(starts, counts)]
    for result, dest in zip(_render_all(items, outs), outs):
        for name, image in result.items():
            if not np.may_share_memory(image, dest[name]):
                dest[name][...] = image


def _render_all(items: Sequence[tuple], outs: Sequence[dict[str, np.ndarray] | None]) -> list[dict[str, np.ndarray]]:
    checked = [(r, r._checked_poses(poses, show), bool(show), checked_time(time[0]) if time else 0.0)
               for r, poses, show, *time in items]
    results: list[dict[str, np.ndarray] | None] = [None] * len(checked)
    plans, later = [], []
    joint_time: dict[int, float] = {}  # id(renderer) -> the time of its first native batch
    mounts = _camera_poses_of_all(checked)
    for k, (r, poses, show, time) in enumerate(checked):
        native = len(poses) and getattr(r, "tracer", None) == "native"
        if native and (joint_time.setdefault(id(r), time) == time or not r.moving):
            r.place(time)
            plans.append((k, r, r._plan(poses, show, mounts.get(k), outs[k])))
        elif native:
            later.append(k)
        elif outs[k] is not None and hasattr(r, "render_into"):   # egl: read back straight into out
            results[k] = r.render_into(poses, show, time, outs[k])
        else:
            results[k] = r.render(poses, show, time)
    if plans:
        from visfly_dist.scene_worker.render_native import trace

        trace([b for _, _, plan in plans for b in plan.batches], max(r.threads for _, r, _ in plans))
        for k, r, plan in plans:
            results[k] = r._finish(plan)
    for k in later:
        r, poses, show, time = checked[k]
        results[k] = r.render(poses, show, time)
    return results  # type: ignore[return-value]


def _camera_poses_of_all(checked: Sequence[tuple]) -> dict[int, list[tuple[np.ndarray, np.ndarray]]]:
    """Camera poses of the native-traced items that carry the first such item's cameras, computed
    over all their drones at once: item ``k`` -> ``[(origins, rotations)]`` per camera (its rows)."""
    native = [k for k, (r, poses, _, _) in enumerate(checked) if len(poses) and getattr(r, "tracer", None) == "native"]
    cameras = checked[native[0]][0].cameras if native else ()
    same = [k for k in native if checked[k][0].cameras == cameras]
    if len(same) < 2:
        return {}
    poses = np.concatenate([checked[k][1] for k in same])
    mounts = [camera_world_poses(poses, cam) for cam in cameras]
    ends = np.cumsum([len(checked[k][1]) for k in same])
    return {k: [(o[end - len(checked[k][1]):end], m[end - len(checked[k][1]):end]) for o, m in mounts]
            for k, end in zip(same, ends.tolist())}


@functools.lru_cache(maxsize=1)
def available_backends() -> tuple[str, ...]:
    """The backends whose libraries are installed (cheap check; nothing is initialised)."""
    from visfly_dist.scene_worker import render_native

    out = []
    if importlib.util.find_spec("embreex") is not None or render_native.available():
        out.append("raycast")
    if importlib.util.find_spec("OpenGL") is not None and ctypes.util.find_library("EGL") is not None:
        out.append("egl")
    return tuple(out)


def choose_backend(requested: str, cameras: Sequence[CameraSpec]) -> tuple[str, str]:
    """Resolve a backend request, with the reason.

    ``auto`` takes the fastest backend able to give what the cameras ask for. ``egl`` only when its
    EGL device is a GPU (``GL_RENDERER`` not llvmpipe/softpipe, see
    :func:`visfly_dist.scene_worker.render_egl.gl_device`) and a camera is RGB or larger than the
    raycast limit (rasterising costs less per pixel than tracing there); else ``raycast`` (exact
    depth and segmentation, textured RGB too, and the cheaper at small sizes and on a CPU: Mesa's
    llvmpipe rasterises slower than the tracers trace). The limit depends on the tracer. Measured on
    garage-stones, 100 cameras, CPU time per depth frame (every thread of the process), one run of
    ``visfly-dist bench render`` on a loaded 2-core machine:

    ======  ==============  =========  ===============
    size    native packets  embreex    egl (llvmpipe)
    ======  ==============  =========  ===============
    64      0.29 ms         0.75 ms    2.1 ms
    128     0.74 ms         2.9 ms     2.6 ms
    256     2.4 ms          10.6 ms    3.0 ms
    ======  ==============  =========  ===============

    (egl there is the per-camera renderer before issue 23; the batch renderer takes about half its
    CPU per depth frame on llvmpipe at 64x64, still more than the native tracer: BENCHMARKS.md.) So on a GPU: native up to
    ``NATIVE_RAYCAST_MAX_PIXELS`` (256x256), embreex up to ``RAYCAST_MAX_PIXELS`` (128x128); GPU
    rates are not measured yet, so these CPU-derived limits are kept there.

    The EGL device is probed (a context made, once per process) only when ``auto`` would take
    ``egl`` on a GPU; a device that fails counts as unavailable.

    Returns:
        ``(backend name, reason)``.
    """
    from visfly_dist.scene_worker import render_native

    if requested not in BACKEND_CHOICES:
        raise ConfigError(f"backend={requested!r} must be one of {BACKEND_CHOICES}")
    available = available_backends()
    if requested != "auto":
        if requested not in available:
            raise ConfigError(f"backend {requested!r} is not available here (available: {list(available)}); "
                              "install its libraries (embreex or the native tracer for raycast; PyOpenGL + libEGL for egl) "
                              "or pick another")
        return requested, "requested"
    if not available:
        raise ConfigError("no render backend is available; install embreex (raycast) or PyOpenGL + libEGL (egl)")
    if "raycast" not in available:
        return "egl", "raycast (native tracer or embreex) unavailable"
    if "egl" not in available:
        return "raycast", "EGL unavailable (RGB, if asked for, from the tracer's shading)"
    limit, tracer = ((NATIVE_RAYCAST_MAX_PIXELS, "native") if render_native.available()
                     else (RAYCAST_MAX_PIXELS, "embreex"))
    if any(c.kind == "rgb" for c in cameras):
        why = "an RGB camera: rasterised on the GPU"
    elif any(c.width * c.height > limit for c in cameras):
        why = f"a camera has more than {limit} pixels: rasterising on the GPU is cheaper there than {tracer} tracing"
    else:
        return "raycast", "small depth/segmentation cameras: raycast is exact and fastest"
    device = egl_device()
    if device is None:
        return "raycast", "GPU EGL unavailable (no usable EGL device)"
    if not device.is_gpu:
        return "raycast", f"GPU EGL unavailable (the EGL device is {device.renderer!r}, a CPU rasteriser, slower than tracing)"
    return "egl", f"{why} ({device.renderer})"


def gl_device_name(backend: str) -> str | None:
    """The ``GL_RENDERER`` of the EGL device a worker of ``backend`` draws with (``auto``: may draw
    with), for its ready line and health; None for ``raycast`` or without a usable device (``auto``).

    Raises:
        ConfigError: ``egl`` was asked for and there is no usable EGL device (the message says to
            use ``--backend raycast``).
    """
    if backend == "raycast" or "egl" not in available_backends():
        return None
    if backend == "egl":
        from visfly_dist.scene_worker.render_egl import gl_device

        return gl_device().renderer
    device = egl_device()
    return None if device is None else device.renderer


def egl_device():
    """The EGL device of this process (:func:`visfly_dist.scene_worker.render_egl.gl_device`), or None
    when there is none usable."""
    from visfly_dist.scene_worker.render_egl import gl_device

    try:
        return gl_device()
    except ConfigError as exc:
        log.info("no EGL device: %s", exc)
        return None


def resolve_backend(requested: str, cameras: Sequence[CameraSpec]) -> str:
    """The backend name for ``requested`` (``auto``, ``egl`` or ``raycast``); logs why."""
    name, reason = choose_backend(requested, cameras)
    log.info("render backend %s (%s)", name, reason)
    return name


def make_renderer(backend: str, scene: Scene, cameras: Sequence[CameraSpec], drone_radius: float = 0.1,
                  threads: int | None = None, **options: Any) -> Renderer:
    """Build a renderer.

    Args:
        backend: ``"egl"``, ``"raycast"`` or ``"auto"`` (see :func:`choose_backend`).
        scene: the scene to draw.
        cameras: the cameras mounted on every drone.
        drone_radius: radius of the spheres drawn for other drones, metres.
        threads: raycast tracing threads (None: the CPUs this process may use, at most 8); egl ignores it.
        **options: backend options (``raycast``: ``tracer``).
    """
    name = resolve_backend(backend, cameras)
    if name == "raycast":
        from visfly_dist.scene_worker.render_raycast import RaycastRenderer

        return RaycastRenderer(scene, cameras, drone_radius, threads=threads, **options)
    from visfly_dist.scene_worker.render_egl_batch import BatchEglRenderer

    return BatchEglRenderer(scene, cameras, drone_radius, **options)
