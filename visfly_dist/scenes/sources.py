"""Turning a scene source string into a :class:`Scene`: ``gen:`` specs and paths under roots.

Sources are what travels on the wire (``LoadScene``), so a path is only accepted when it resolves
(``..`` and symlinks followed) inside one of the worker's configured roots.

A mesh file path may carry load options after a ``?``, so they travel in the source string and the
wire needs no field for them: ``rooms/hall.glb?up=z`` loads a z-up glb (``up`` is ``y`` or ``z``; the
default is the format's, see :mod:`visfly_dist.scenes.meshes`). Options are recognised after the
last ``?`` when that part holds a ``=`` or the path before it ends in a mesh suffix; anything but
``up=y|z`` on a mesh file is refused.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any, Iterable
from urllib.parse import parse_qsl

from visfly_dist.errors import ErrorCode, SceneError
from visfly_dist.scenes.generators import generate_scene, parse_value
from visfly_dist.scenes.paths import PathLike, is_inside, normalize_roots
from visfly_dist.scenes.scene import Scene
from visfly_dist.scenes.source_syntax import GEN_PREFIX, split_path_source
from visfly_dist.scenes.storage import load_scene

GENERATED_CACHE_SIZE = 8


def parse_gen_spec(spec: str) -> tuple[str, int, dict[str, Any]]:
    """Split ``gen:KIND?seed=S&key=value`` into ``(kind, seed, params)``; seed defaults to 0.

    Values are parsed as int, float, or comma-separated floats (tuples).
    """
    if not spec.startswith(GEN_PREFIX):
        raise SceneError(f"scene spec {spec!r} must start with {GEN_PREFIX!r}, e.g. 'gen:garage-stones?seed=3&density=0.15'")
    kind, _, query = spec[len(GEN_PREFIX):].partition("?")
    try:
        pairs = parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query))
    except ValueError as exc:
        raise SceneError(f"scene spec {spec!r}: query must be key=value pairs joined by '&' ({exc})") from exc
    params: dict[str, Any] = {}
    for key, text in pairs:
        if key in params:
            raise SceneError(f"scene spec {spec!r} sets {key!r} twice")
        params[key] = parse_value(text)
    seed = params.pop("seed", 0)
    if not isinstance(seed, int):
        raise SceneError(f"scene spec {spec!r}: seed={seed!r} must be an int >= 0")
    return kind, seed, params


def resolve_source(source: str, roots: Iterable[PathLike]) -> Scene:
    """The scene named by ``source``: a ``gen:`` spec, or a path inside one of ``roots``.

    Generated scenes are cached in-process (LRU of :data:`GENERATED_CACHE_SIZE` specs): the same
    Scene object is returned for the same spec, so callers must treat scenes as read-only.

    Args:
        source: ``"gen:KIND?seed=S&key=value"``, or a path relative to a root (tried in order), or
            an absolute path inside a root; a mesh file path may end in ``?up=y|z``.
        roots: directories scene files may be read from.

    Raises:
        SceneError: a path outside every root, a missing file, or a bad spec.
    """
    if not isinstance(source, str) or not source:
        raise SceneError(f"scene source {source!r} must be a non-empty string: a 'gen:' spec or a path under the scene roots")
    if source.startswith(GEN_PREFIX):
        kind, seed, params = parse_gen_spec(source)
        return _generated(kind, seed, tuple(sorted(params.items())))
    resolved_roots = normalize_roots(roots) or []
    if not resolved_roots:
        raise SceneError(f"scene path {source!r} given but no scene roots are configured; use a 'gen:' spec or add a root")
    path_text, options = split_path_source(source)
    path = Path(path_text)
    candidates = [path] if path.is_absolute() else [root / path for root in resolved_roots]
    inside = [c for c in candidates if is_inside(c, resolved_roots)]
    if not inside:
        raise SceneError(
            f"scene path {source!r} resolves outside the scene roots {[str(r) for r in resolved_roots]}; "
            f"give a path relative to a root"
        )
    for candidate in inside:
        if candidate.exists():
            return load_scene(candidate, up_axis=options.get("up"), roots=resolved_roots)
    raise SceneError(f"scene path {source!r} not found under the scene roots {[str(r) for r in resolved_roots]}",
                     code=ErrorCode.SCENE_MISSING)


@lru_cache(maxsize=GENERATED_CACHE_SIZE)
def _generated(kind: str, seed: int, params: tuple[tuple[str, Any], ...]) -> Scene:
    return generate_scene(kind, seed, **dict(params))
