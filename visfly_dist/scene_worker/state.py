"""The worker's scene table: every loaded scene with its renderer and obstacle queries."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from visfly_dist.errors import SceneError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.messages import LoadScene
from visfly_dist.scene_worker.queries import ObstacleQueries
from visfly_dist.scene_worker.render_base import Renderer, make_renderer
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
    """

    key: str
    scene: Scene
    cameras: tuple[CameraSpec, ...]
    renderer: Renderer
    queries: ObstacleQueries
    multi_agent: bool


def build_scene(request: LoadScene, roots: Sequence[Path], backend: str, threads: int | None = None) -> LoadedScene:
    """Resolve a load request's source under ``roots`` and build its renderer and queries.

    Args:
        request: the validated ``load_scene`` request.
        roots: directories scene files may come from (never empty: no unconfined reads).
        backend: ``auto``, ``egl`` or ``raycast``; ``auto`` picks per the request's cameras.
        threads: raycast tracing threads (None: the renderer's default).

    Raises:
        SceneError: the source is unknown, unreadable or outside ``roots``.
        ConfigError: the backend cannot render these cameras.
    """
    assert roots, "a worker always has at least one scene root"
    scene = resolve_source(request.source, list(roots))
    renderer = make_renderer(backend, scene, request.cameras, drone_radius=request.drone_radius, threads=threads)
    try:
        queries = ObstacleQueries(scene, drone_radius=request.drone_radius)
    except BaseException:
        renderer.close()
        raise
    return LoadedScene(request.scene_key, scene, request.cameras, renderer, queries, request.multi_agent)


class SceneTable:
    """Loaded scenes by key. Not thread-safe: the worker uses it from its serving thread only."""

    def __init__(self) -> None:
        self._scenes: dict[str, LoadedScene] = {}

    def put(self, loaded: LoadedScene) -> None:
        """Add a scene, replacing (and closing) one loaded under the same key."""
        old = self._scenes.pop(loaded.key, None)
        self._scenes[loaded.key] = loaded
        if old is not None:
            old.renderer.close()

    def get(self, key: str) -> LoadedScene:
        """The scene loaded under ``key``; SceneError naming the loaded keys otherwise."""
        try:
            return self._scenes[key]
        except KeyError:
            raise SceneError(
                f"scene_key {key!r} is not loaded on this worker; loaded: {self.keys()}; "
                "send load_scene first"
            ) from None

    def remove(self, key: str) -> None:
        """Forget the scene under ``key`` and close its renderer."""
        self.get(key).renderer.close()
        del self._scenes[key]

    def keys(self) -> list[str]:
        return sorted(self._scenes)

    def close(self) -> None:
        """Close every renderer; the table is empty afterwards. Idempotent."""
        while self._scenes:
            _, loaded = self._scenes.popitem()
            loaded.renderer.close()
