"""The syntax of scene source strings, checked without loading anything.

A source is a ``gen:`` spec or a path under the scene roots, a mesh path possibly carrying load
options after ``?`` (:mod:`visfly_dist.scenes.sources`). This module imports nothing heavy, so the
learner checks its sources before any worker starts without importing the mesh stack.
"""

from __future__ import annotations

from visfly_dist.errors import SceneError

GEN_PREFIX = "gen:"
MESH_SUFFIXES = (".glb", ".gltf", ".obj", ".ply", ".stl")
UP_AXES = ("y", "z")
PATH_OPTIONS = {"up": UP_AXES}
"""Options a mesh-file source may carry after ``?``, with their accepted values."""


def split_path_source(source: str) -> tuple[str, dict[str, str]]:
    """Split a path source into the path and its validated options (module docstring).

    ``"rooms/hall.glb?up=z"`` gives ``("rooms/hall.glb", {"up": "z"})``; a source without options
    gives ``(source, {})``.

    Raises:
        SceneError: malformed options, an unknown option or value, or options on a non-mesh path.
    """
    path, sep, query = source.rpartition("?")
    if not sep or "/" in query or not ("=" in query or path.lower().endswith(MESH_SUFFIXES)):
        return source, {}
    accepted = ", ".join(f"{k}={'|'.join(v)}" for k, v in PATH_OPTIONS.items())
    if not path.lower().endswith(MESH_SUFFIXES):
        raise SceneError(f"scene source {source!r}: options ({accepted}) apply to mesh files {list(MESH_SUFFIXES)} only")
    options: dict[str, str] = {}
    for item in query.split("&"):
        key, eq, value = item.partition("=")
        if not eq or key not in PATH_OPTIONS or value not in PATH_OPTIONS[key] or key in options:
            raise SceneError(f"scene source {source!r}: option {item!r} is not valid; accepted: {accepted}, "
                             f"each at most once, joined by '&', e.g. 'room.glb?up=z'")
        options[key] = value
    return path, options
