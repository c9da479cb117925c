"""The EGL context of the ``egl`` backend: headless OpenGL on a GPU, or on Mesa's llvmpipe (CPU).

No X11 library is involved: the context is made on an EGL *device* display (``EGL_EXT_device_base``
and ``EGL_EXT_platform_device``) with no surface, and nothing here imports pyrender or pyglet.

The device is, in this order:

1. ``EGL_DEVICE_ID`` (an index into the EGL devices of the host), if set;
2. the first index listed in ``CUDA_VISIBLE_DEVICES``, if set (the GPU a job was given);
3. device 0.

One context per process, made on first use (:func:`gl_context`) and kept until the process exits.
On a CPU rasteriser (llvmpipe) the process also keeps freed heap memory instead of handing it back
to the kernel at once (:func:`keep_freed_heap`).
Renderers make it current before they draw, so draw from one thread at a time; :func:`gl_device`
names the device (``GL_RENDERER``) and can be asked from any thread (it never leaves the context
current on a thread that did not have it).
"""

from __future__ import annotations

import ctypes
import logging
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")  # must precede the first OpenGL import

from visfly_dist.errors import ConfigError  # noqa: E402

log = logging.getLogger(__name__)

EGL_PLATFORM_DEVICE_EXT = 0x313F
EGL_DRM_DEVICE_FILE_EXT = 0x3233
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swrast", "software rasterizer")
"""``GL_RENDERER`` substrings of CPU rasterisers: the ``egl`` backend there is not a GPU."""

HEAP_KEPT_BYTES = 256 << 20
"""Freed heap memory glibc keeps for reuse on a CPU rasteriser (:func:`keep_freed_heap`)."""
HEAP_MMAP_BYTES = 32 << 20
"""Blocks from this size up get their own mapping (glibc's ceiling for its own adaptive threshold)."""
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3   # glibc's mallopt parameters

_lock = threading.Lock()
_context: "EglContext | None" = None
_lanes_lock = threading.Lock()
_lanes: "list[tuple[EglContext, ThreadPoolExecutor]]" = []


@dataclass
class EglContext:
    """A surfaceless OpenGL (3.3+ core) context on one EGL device."""

    display: object
    context: object
    config: object
    device_index: int
    device_source: str
    renderer: str = ""
    version: str = ""
    _thread: int | None = None

    def make_current(self) -> None:
        """Make the context current on the calling thread (no-op when it already is)."""
        from OpenGL import EGL

        if self._thread == threading.get_ident():
            return
        if not EGL.eglMakeCurrent(self.display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, self.context):
            raise ConfigError(f"eglMakeCurrent failed (error 0x{EGL.eglGetError():x}); is the context current on "
                              "another thread? render from one thread at a time")
        self._thread = threading.get_ident()

    def release(self) -> None:
        """Make no context current on the calling thread (if this one is)."""
        from OpenGL import EGL

        if self._thread == threading.get_ident():
            EGL.eglMakeCurrent(self.display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)
            self._thread = None

    @property
    def is_gpu(self) -> bool:
        """Whether the device is a GPU (``GL_RENDERER`` is not a CPU rasteriser such as llvmpipe)."""
        name = self.renderer.lower()
        return bool(name) and not any(s in name for s in SOFTWARE_RENDERERS)


def egl_device_index() -> tuple[int, str]:
    """The EGL device index to use and where it came from (module docstring)."""
    value = os.environ.get("EGL_DEVICE_ID", "").strip()
    if value:
        if not value.isdigit():
            raise ConfigError(f"EGL_DEVICE_ID={value!r} must be a device index (0, 1, ...)")
        return int(value), "EGL_DEVICE_ID"
    first = os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",")[0].strip()
    if first.isdigit():
        return int(first), "CUDA_VISIBLE_DEVICES"
    return 0, "default"


def gl_context() -> EglContext:
    """This process's EGL context, current on the calling thread (made on first use).

    Raises:
        ConfigError: no usable EGL device (the message says what is missing and to use
            ``--backend raycast``).
    """
    global _context
    with _lock:
        if _context is None:
            _context = _create()
    _context.make_current()
    return _context


def gl_device() -> EglContext:
    """The process's context (made if needed) without leaving it current on a thread that did not
    have it: for its ``renderer`` string (``GL_RENDERER``) and ``is_gpu``, from any thread."""
    global _context
    with _lock:
        if _context is None:
            _context = _create()
            _context.release()
    return _context


def extra_context() -> EglContext:
    """Another context on the process's EGL device (current nowhere): for drawing from a second
    thread at the same time (each thread keeps its own context current)."""
    from OpenGL import EGL, arrays

    main = gl_device()
    attributes = arrays.GLintArray.asArray([
        EGL.EGL_CONTEXT_MAJOR_VERSION, 3, EGL.EGL_CONTEXT_MINOR_VERSION, 3,
        EGL.EGL_CONTEXT_OPENGL_PROFILE_MASK, EGL.EGL_CONTEXT_OPENGL_CORE_PROFILE_BIT, EGL.EGL_NONE])
    with _lock:
        EGL.eglBindAPI(EGL.EGL_OPENGL_API)
        context = EGL.eglCreateContext(main.display, main.config, EGL.EGL_NO_CONTEXT, attributes)
    if not context:
        raise _fail(f"a second OpenGL context on device {main.device_index} failed (error 0x{EGL.eglGetError():x})")
    return EglContext(main.display, context, main.config, main.device_index, main.device_source, main.renderer,
                      main.version)


def drawing_lanes(count: int) -> "list[tuple[EglContext, ThreadPoolExecutor]]":
    """The first ``count`` extra drawing lanes of this process: each another context on the device
    (:func:`extra_context`), current on its own thread, the executor of that one thread. Made on
    first use and kept until the process exits, shared by every renderer (an llvmpipe context
    holds about 24 MB, so one per renderer and core would add up over a worker's scenes)."""
    with _lanes_lock:
        while len(_lanes) < count:
            context = extra_context()
            lane = ThreadPoolExecutor(1, thread_name_prefix="egl-lane")
            lane.submit(context.make_current).result()
            _lanes.append((context, lane))
        return _lanes[:count]


def _fail(what: str) -> ConfigError:
    return ConfigError(f"the egl backend has no usable EGL device: {what}; use --backend raycast "
                       "(or set EGL_DEVICE_ID to another device)")


def _create() -> EglContext:
    if os.environ.get("PYOPENGL_PLATFORM") != "egl":
        raise _fail(f"PYOPENGL_PLATFORM={os.environ.get('PYOPENGL_PLATFORM')!r} but it must be 'egl' "
                    "(unset it before the first OpenGL import)")
    try:
        from OpenGL import EGL, arrays
    except Exception as exc:   # no libEGL, or OpenGL imported earlier with another platform
        raise _fail(f"PyOpenGL's EGL platform did not load ({type(exc).__name__}: {exc})") from exc
    index, source = egl_device_index()
    devices = _query_devices(EGL)
    if devices is None:    # no device enumeration: only the default display
        if index != 0:
            raise _fail(f"EGL device {index} (from {source}) asked for but this EGL cannot enumerate devices")
        display = EGL.eglGetDisplay(EGL.EGL_DEFAULT_DISPLAY)
    else:
        if index >= len(devices):
            raise _fail(f"EGL device {index} (from {source}) asked for but the host has {len(devices)} EGL device(s)")
        get_platform_display = _egl_function(EGL, "eglGetPlatformDisplayEXT", EGL.EGLDisplay,
                                             ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p)
        display = get_platform_display(EGL_PLATFORM_DEVICE_EXT, devices[index], None)
    major, minor = EGL.EGLint(), EGL.EGLint()
    if not display or not EGL.eglInitialize(display, ctypes.pointer(major), ctypes.pointer(minor)):
        raise _fail(f"eglInitialize failed on device {index} (from {source})")
    config_attributes = arrays.GLintArray.asArray([
        EGL.EGL_SURFACE_TYPE, EGL.EGL_PBUFFER_BIT, EGL.EGL_RENDERABLE_TYPE, EGL.EGL_OPENGL_BIT, EGL.EGL_NONE])
    configs, count = (EGL.EGLConfig * 1)(), EGL.EGLint()
    if not EGL.eglChooseConfig(display, config_attributes, configs, 1, ctypes.pointer(count)) or count.value < 1:
        raise _fail(f"device {index} has no OpenGL config")
    if not EGL.eglBindAPI(EGL.EGL_OPENGL_API):
        raise _fail(f"device {index} does not offer desktop OpenGL")
    context_attributes = arrays.GLintArray.asArray([
        EGL.EGL_CONTEXT_MAJOR_VERSION, 3, EGL.EGL_CONTEXT_MINOR_VERSION, 3,
        EGL.EGL_CONTEXT_OPENGL_PROFILE_MASK, EGL.EGL_CONTEXT_OPENGL_CORE_PROFILE_BIT, EGL.EGL_NONE])
    context = EGL.eglCreateContext(display, configs[0], EGL.EGL_NO_CONTEXT, context_attributes)
    if not context:
        raise _fail(f"device {index} gave no OpenGL 3.3 core context (error 0x{EGL.eglGetError():x})")
    made = EglContext(display, context, configs[0], index, source)
    made.make_current()
    from OpenGL import GL

    made.renderer = (GL.glGetString(GL.GL_RENDERER) or b"").decode(errors="replace")
    made.version = (GL.glGetString(GL.GL_VERSION) or b"").decode(errors="replace")
    log.info("EGL device %d (%s): %s, OpenGL %s", index, source, made.renderer, made.version)
    if not made.is_gpu:
        keep_freed_heap()
    return made


def keep_freed_heap() -> bool:
    """Have glibc keep up to :data:`HEAP_KEPT_BYTES` of freed heap memory for reuse (process-wide).

    llvmpipe bins every frame's triangles in fresh heap blocks (about 15 MB for 100 cameras of 64x64)
    and frees them once it has rasterised. Unless its adaptive thresholds have grown (big blocks
    freed earlier in the process), glibc hands that memory back to the kernel at once and the next
    frame faults it in again, page by page: in a fresh process a fifth of a render's CPU time (in
    the kernel), and lock contention between contexts drawing at once. Setting the trim
    threshold turns glibc's adaptive mapping threshold off, so that one is set where the adaptive
    one would end (:data:`HEAP_MMAP_BYTES`). Returns whether the settings took (False off glibc).
    """
    try:
        libc = ctypes.CDLL(None)
        return bool(libc.mallopt(_M_TRIM_THRESHOLD, HEAP_KEPT_BYTES)) and bool(
            libc.mallopt(_M_MMAP_THRESHOLD, HEAP_MMAP_BYTES))
    except (OSError, AttributeError):   # no mallopt: not glibc
        return False


def _egl_function(EGL, name: str, result, *args):  # noqa: N803 (the module)
    address = EGL.eglGetProcAddress(name)
    if not address:
        return None
    prototype = ctypes.CFUNCTYPE(result, *args)
    return prototype(address)


def _query_devices(EGL) -> list | None:  # noqa: N803
    """The EGL devices (opaque pointers), or None when the extension is missing."""
    query = _egl_function(EGL, "eglQueryDevicesEXT", ctypes.c_uint,
                          ctypes.c_int, ctypes.POINTER(ctypes.c_void_p), ctypes.POINTER(ctypes.c_int))
    if query is None or _egl_function(EGL, "eglGetPlatformDisplayEXT", ctypes.c_void_p) is None:
        return None
    count = ctypes.c_int()
    if not query(0, None, ctypes.byref(count)):
        return []
    devices = (ctypes.c_void_p * max(count.value, 1))()
    if count.value and not query(count.value, devices, ctypes.byref(count)):
        return []
    return [devices[i] for i in range(count.value)]
