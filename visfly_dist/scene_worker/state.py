"""The worker's scene table: every loaded (or loading) scene with its renderer and queries.

A load has two halves. :func:`prepare_scene` does the CPU-heavy part (mesh loading or generation,
the FCL and Embree builds) on any thread; :func:`assemble_scene` runs on the serving thread and
builds what must live there (an EGL renderer: its GL context belongs to the thread that renders).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from visfly_dist.errors import ConfigError, ErrorCode, SceneError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.messages import LoadScene
from visfly_dist.scene_worker.queries import ObstacleQueries
from visfly_dist.scene_worker.render_base import Renderer, make_renderer, resolve_backend
from visfly_dist.scenes import resolve_source
from visfly_dist.scenes.scene import Scene


@dataclass
class LoadedScene:
    """One scene as the worker serves it.

    Attributes:
        key: the ``scene_key`` requests name it by.
        scene: the meshes, bounds and metadata.
        cameras: the sensors rendered for every agent.
        renderer: renders ``cameras`` of many poses at once.
        queries: nearest obstacle and collision per position.
        multi_agent: agents see each other (drones are drawn in the images).
        built_by: the load that built it (keys that share it keep their first key's).
    """

    key: str
    scene: Scene
    cameras: tuple[CameraSpec, ...]
    renderer: Renderer
    queries: ObstacleQueries
    multi_agent: bool
    built_by: LoadScene

    def shared_as(self, key: str) -> "LoadedScene":
        """The same scene served under another key (nothing is copied or built)."""
        return LoadedScene(key, self.scene, self.cameras, self.renderer, self.queries, self.multi_agent, self.built_by)

    @property
    def pixels_per_agent(self) -> int:
        """Pixels one agent costs to render: the sum over its cameras of width x height."""
        return sum(c.width * c.height for c in self.cameras)


@dataclass
class PreparedScene:
    """The thread-independent half of a load: scene, queries, and the renderer unless it is EGL."""

    request: LoadScene
    scene: Scene
    queries: ObstacleQueries
    renderer: Renderer | None

    def discard(self) -> None:
        if self.renderer is not None:
            self.renderer.close()


def same_scene(a: LoadScene, b: LoadScene) -> bool:
    """Whether two loads build the same scene: same source, cameras, drone radius and multi-agent drawing."""
    return (a.source == b.source and tuple(a.cameras) == tuple(b.cameras) and a.drone_radius == b.drone_radius
            and a.multi_agent == b.multi_agent)


def prepare_scene(request: LoadScene, roots: Sequence[Path], backend: str, threads: int | None = None,
                  scene: Scene | None = None) -> PreparedScene:
    """Resolve a load request's source under ``roots``; build its queries and (unless EGL) renderer.

    Safe on any thread. Args as :func:`assemble_scene`'s inputs: the validated request, the scene
    roots (never empty: no unconfined reads) and the backend (``auto``, ``egl`` or ``raycast``);
    ``scene``: the source already resolved (generated in a child process), else it is resolved here.

    Raises:
        SceneError: the source is unknown, unreadable, outside ``roots``, or this worker's backend
            cannot render its cameras.
    """
    assert roots, "a worker always has at least one scene root"
    if scene is None:
        scene = resolve_source(request.source, list(roots))
    queries = ObstacleQueries(scene, drone_radius=request.drone_radius, threads=threads)
    renderer = None
    if _backend_for(request, backend) != "egl":
        renderer = _renderer(request, scene, backend, threads)
    return PreparedScene(request, scene, queries, renderer)


def assemble_scene(prepared: PreparedScene, backend: str) -> LoadedScene:
    """Finish a load on the serving thread (builds an EGL renderer there)."""
    request = prepared.request
    renderer = prepared.renderer or _renderer(request, prepared.scene, backend)
    return LoadedScene(request.scene_key, prepared.scene, request.cameras, renderer, prepared.queries,
                       request.multi_agent, request)


def _backend_for(request: LoadScene, backend: str) -> str:
    try:
        return resolve_backend(backend, request.cameras)
    except ConfigError as exc:
        raise SceneError(f"this worker cannot render scene {request.scene_key!r}: {exc}") from None


def _renderer(request: LoadScene, scene: Scene, backend: str, threads: int | None = None) -> Renderer:
    try:
        return make_renderer(backend, scene, request.cameras, drone_radius=request.drone_radius, threads=threads)
    except ConfigError as exc:
        raise SceneError(f"this worker cannot render scene {request.scene_key!r}: {exc}") from None


_NO_LOOKUP: tuple[tuple[str, ...], tuple, bool] = ((), (), True)
"""``SceneTable``'s remembered lookup when there is none (no keys, no scenes)."""


class SceneTable:
    """Loaded scenes by key, and the keys whose load is in progress.

    Not thread-safe: the worker uses it from its serving thread only. A key being re-loaded keeps
    serving its old scene until the new one is put in its place.
    """

    def __init__(self) -> None:
        self._scenes: dict[str, LoadedScene] = {}
        self._loading: dict[str, Any] = {}
        # The last lookup()'s keys and answer; any change to the loaded scenes clears it.
        self._last: tuple[tuple[str, ...], tuple[LoadedScene, ...], bool] = _NO_LOOKUP

    def put(self, loaded: LoadedScene) -> None:
        """Add a scene, replacing (and closing) one loaded under the same key."""
        self._last = _NO_LOOKUP
        old = self._scenes.pop(loaded.key, None)
        self._scenes[loaded.key] = loaded
        if old is not None:
            self._release(old)

    def serving(self, request: LoadScene) -> LoadedScene | None:
        """A loaded scene that is what ``request`` would build (:func:`same_scene`), if any: its meshes,
        renderer and queries can serve the request's key too."""
        return next((s for s in self._scenes.values() if same_scene(s.built_by, request)), None)

    def _release(self, gone: LoadedScene) -> None:
        """Close the renderer of a scene no longer served, unless another key shares it."""
        if not any(s.renderer is gone.renderer for s in self._scenes.values()):
            gone.renderer.close()

    def get(self, key: str) -> LoadedScene:
        """The scene loaded under ``key``; SceneError (``scene_loading`` or ``unknown_scene``) otherwise."""
        try:
            return self._scenes[key]
        except KeyError:
            if key in self._loading:
                raise SceneError(f"scene_key {key!r} is still loading on this worker; wait for its load reply",
                                 code=ErrorCode.SCENE_LOADING) from None
            raise SceneError(
                f"scene_key {key!r} is not loaded on this worker; loaded: {self.keys()}; send load_scene first",
                code=ErrorCode.UNKNOWN_SCENE,
            ) from None

    def lookup(self, keys: tuple[str, ...]) -> tuple[tuple[LoadedScene, ...], bool]:
        """The scene of every key, in order, and whether they all carry the same cameras.

        Steps name the same keys request after request: the answer for the last keys is kept
        until a scene is put or removed. SceneError as :meth:`get` for the first key not loaded.
        """
        last_keys, found, same_cameras = self._last
        if keys == last_keys:
            return found, same_cameras
        try:
            found = tuple([self._scenes[key] for key in keys])
        except KeyError:
            found = tuple([self.get(key) for key in keys])  # raises for the first key not loaded
        cameras = found[0].cameras if found else ()
        same_cameras = all(s.cameras is cameras or s.cameras == cameras for s in found)
        self._last = (keys, found, same_cameras)
        return found, same_cameras

    def remove(self, key: str) -> Any | None:
        """Forget the scene under ``key`` (closing its renderer) and its load in progress, if any.

        Returns:
            The token of the load in progress that was dropped, or ``None``.
        """
        self._last = _NO_LOOKUP
        job = self._loading.pop(key, None)
        if job is None or key in self._scenes:
            gone = self.get(key)  # SceneError for a key neither loaded nor loading
            del self._scenes[key]
            self._release(gone)
        return job

    def begin_load(self, key: str, job: Any) -> None:
        """Mark ``key`` as loading, with ``job`` as the token that :meth:`end_load` must present."""
        assert key not in self._loading, key
        self._loading[key] = job

    def end_load(self, key: str, job: Any) -> bool:
        """Clear the loading mark of ``key`` if ``job`` still owns it; False if it was dropped."""
        if not self.owns_load(key, job):
            return False
        del self._loading[key]
        return True

    def owns_load(self, key: str, job: Any) -> bool:
        """Whether ``job`` is still the load in progress of ``key`` (not cancelled by an unload)."""
        return self._loading.get(key) is job

    def is_loading(self, key: str) -> bool:
        return key in self._loading

    def __contains__(self, key: str) -> bool:
        return key in self._scenes or key in self._loading

    def __len__(self) -> int:
        """Scenes loaded or loading."""
        return len(self._scenes.keys() | self._loading.keys())

    def keys(self) -> list[str]:
        return sorted(self._scenes)

    def loading_jobs(self) -> list[Any]:
        """The tokens of the loads in progress."""
        return list(self._loading.values())

    def loading_keys(self) -> list[str]:
        return sorted(self._loading)

    def pop_loading(self) -> list[Any]:
        """Drop every load in progress; returns their tokens."""
        jobs, self._loading = list(self._loading.values()), {}
        return jobs

    def close(self) -> None:
        """Close every renderer; the table is empty afterwards. Idempotent."""
        self._last = _NO_LOOKUP
        self._loading.clear()
        while self._scenes:
            _, loaded = self._scenes.popitem()
            self._release(loaded)
