"""The visfly scene directory format, and :func:`load_scene` for every supported input.

A visfly scene directory holds ``scene.json``::

    {"format": "visfly-scene", "version": 1, "name": ..., "bounds": [[x, y, z], [x, y, z]],
     "metadata": {...}, "objects": [{"name": ..., "id": 1, "mesh": "objects/0001_floor.ply"}, ...]}

and one mesh file per object under ``objects/``: binary PLY (float32 vertices, face or vertex
colours) for coloured objects, GLB for textured ones. Coordinates are stored as they are in the
scene (world, z-up): our own format never goes through the glTF y-up conversion.

A moving obstacle's entry adds ``"motion"`` (a dict of :mod:`visfly_dist.scenes.motion`, e.g.
``{"type": "circle", "centre": [5, 0, 1.5], "radius": 2, "speed": 1}``); its mesh file then holds the
mesh in the object's local frame, placed at the motion's position at each instant.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import trimesh

from visfly_dist.errors import SceneError
from visfly_dist.scenes.habitat import SCENE_INSTANCE_SUFFIX, load_habitat_scene
from visfly_dist.scenes.meshes import MESH_SUFFIXES, load_mesh_file, node_meshes, read_trimesh_scene
from visfly_dist.scenes.motion import motion_from_dict
from visfly_dist.scenes.paths import PathLike, check_inside, normalize_roots
from visfly_dist.scenes.scene import Scene, SceneObject

FORMAT_NAME = "visfly-scene"
FORMAT_VERSION = 1
SCENE_FILE = "scene.json"


def save_scene(scene: Scene, out_dir: PathLike) -> Path:
    """Write ``scene`` as a visfly scene directory (created if needed; an old scene there is replaced,
    its meshes included).

    Returns:
        ``out_dir`` as a Path; ``load_scene`` of it gives the scene back (same names, ids,
        float32-rounded vertices, faces, colours, bounds and metadata).
    """
    out = Path(out_dir)
    (out / "objects").mkdir(parents=True, exist_ok=True)
    entries, written = [], set()
    for obj in scene.objects:
        textured = isinstance(obj.mesh.visual, trimesh.visual.TextureVisuals)
        relative = f"objects/{obj.object_id:04d}_{_safe(obj.name)}.{'glb' if textured else 'ply'}"
        obj.mesh.export(out / relative, file_type="glb" if textured else "ply")
        written.add(out / relative)
        entry = {"name": obj.name, "id": obj.object_id, "mesh": relative}
        if obj.motion is not None:
            entry["motion"] = obj.motion.to_dict()
        entries.append(entry)
    document = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "name": scene.name,
        "bounds": scene.bounds.tolist(),
        "metadata": scene.metadata,
        "objects": entries,
    }
    (out / SCENE_FILE).write_text(json.dumps(document, indent=1, default=_json_default))
    for stale in (out / "objects").iterdir():  # an earlier scene's meshes in this folder: not this scene's
        if stale.is_file() and stale not in written and stale.suffix in (".ply", ".glb"):
            stale.unlink()
    return out


def load_scene(path: PathLike, up_axis: str | None = None, roots: Iterable[PathLike] | None = None) -> Scene:
    """Load a scene from a visfly scene directory (or its scene.json), a mesh file or a Habitat scene.

    Args:
        path: a directory holding ``scene.json``, a ``scene.json``, a ``*.scene_instance.json``, or a
            ``.glb``/``.gltf``/``.obj``/``.ply``/``.stl`` mesh file.
        up_axis: for mesh files only, ``"y"`` or ``"z"``; None takes the format's default (glTF y-up,
            others z-up; see :mod:`visfly_dist.scenes.meshes`).
        roots: when given, every file read must resolve inside one of these directories.

    Raises:
        SceneError: missing file, unsupported kind, malformed content, or a file outside ``roots``.
    """
    resolved_roots = normalize_roots(roots)
    path = Path(path)
    check_inside(path, resolved_roots)
    if path.is_dir():
        if not (path / SCENE_FILE).is_file():
            raise SceneError(f"directory {str(path)!r} has no {SCENE_FILE}; pass a scene directory written by save_scene or a scene file")
        path = path / SCENE_FILE
    if not path.is_file():
        raise SceneError(f"scene file {str(path)!r} does not exist")
    name = path.name.lower()
    if name.endswith(SCENE_INSTANCE_SUFFIX):
        return load_habitat_scene(path, roots=resolved_roots)
    if path.suffix.lower() in MESH_SUFFIXES:
        return load_mesh_file(path, up_axis=up_axis, roots=resolved_roots)
    if path.suffix.lower() == ".json":
        return _load_visfly(path, resolved_roots)
    raise SceneError(
        f"cannot load {str(path)!r}: accepted are a visfly scene directory or {SCENE_FILE}, "
        f"*{SCENE_INSTANCE_SUFFIX} and mesh files {list(MESH_SUFFIXES)}"
    )


def _load_visfly(path: Path, roots: Sequence[Path] | None) -> Scene:
    try:
        document = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SceneError(f"cannot read {str(path)!r}: {exc}") from exc
    if not isinstance(document, dict) or document.get("format") != FORMAT_NAME:
        raise SceneError(f"{str(path)!r} is not a visfly scene file (expected \"format\": {FORMAT_NAME!r})")
    if document.get("version") != FORMAT_VERSION:
        raise SceneError(f"{str(path)!r} has format version {document.get('version')!r}; this build reads version {FORMAT_VERSION}")
    objects = []
    try:
        ids = [int(entry["id"]) for entry in document["objects"]]
        if len(set(ids)) != len(ids) or min(ids, default=1) < 1:
            raise ValueError(f"object ids {ids} must be unique and >= 1")
        # Object files stay inside the scene directory even without configured roots.
        allowed = roots if roots is not None else [path.parent.resolve()]
        for i, entry in enumerate(document["objects"]):
            mesh_path = path.parent / entry["mesh"]
            check_inside(mesh_path, allowed, "scene object mesh")
            motion = motion_from_dict(entry["motion"], f"objects[{i}].motion") if "motion" in entry else None
            objects.append(SceneObject(str(entry["name"]), int(entry["id"]), _read_object_mesh(mesh_path, allowed), motion))
        return Scene(str(document["name"]), objects, np.asarray(document["bounds"], dtype=np.float64), document.get("metadata", {}))
    except (KeyError, TypeError, ValueError) as exc:
        raise SceneError(f"malformed visfly scene file {str(path)!r}: {type(exc).__name__}: {exc}") from exc


def _read_object_mesh(path: Path, roots: Sequence[Path]) -> trimesh.Trimesh:
    if not path.is_file():
        raise SceneError(f"scene object mesh {str(path)!r} does not exist")
    parts = node_meshes(read_trimesh_scene(path, roots))
    if len(parts) != 1:
        raise SceneError(f"scene object mesh {str(path)!r} must hold exactly one mesh, found {len(parts)}")
    return parts[0][1]


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)[:60] or "object"


def _json_default(value: object) -> object:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"scene metadata value {value!r} of type {type(value).__name__} is not JSON-able")
