"""Loading mesh files (glb, gltf, obj, ply, stl) into a :class:`Scene`.

Every node of the file that carries triangles becomes one :class:`SceneObject` with its transform
baked in (world coordinates) and its visual (colours or textures) kept. Object ids are 1, 2, ... in
the order of the node names (sorted, so the numbering is deterministic).

Up axis: our world is z-up. glTF (glb/gltf) is y-up by specification, so by default those files are
rotated +90 deg about x (glTF +y becomes our +z, glTF +z becomes our -y). obj, ply and stl carry no
convention; they are taken as z-up by default. An OBJ file gives one object per ``o`` directive. ``up_axis="y"`` or ``"z"`` overrides the default.
"""  # noqa: E501

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Sequence
from urllib.parse import unquote

import numpy as np
import trimesh

from visfly_dist.errors import SceneError
from visfly_dist.scenes.paths import check_inside
from visfly_dist.scenes.scene import Scene, SceneObject
from visfly_dist.scenes.source_syntax import MESH_SUFFIXES, UP_AXES

log = logging.getLogger(__name__)

# Rotation +90 deg about x: (x, y, z) -> (x, -z, y). Takes a y-up frame (glTF, Habitat) to z-up.
Y_UP_TO_Z_UP = np.array(
    [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


def default_up_axis(path: Path) -> str:
    """``"y"`` for glTF files (y-up by specification), ``"z"`` for every other format."""
    return "y" if path.suffix.lower() in (".glb", ".gltf") else "z"


def read_trimesh_scene(path: Path, roots: Sequence[Path] | None = None) -> trimesh.Scene:
    """Read any supported mesh file as a ``trimesh.Scene`` (vertices kept as stored).

    Raises:
        SceneError: unsupported suffix, unreadable file, or (with ``roots``) a glTF that references
            files outside the roots.
    """
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise SceneError(f"mesh file {str(path)!r} has suffix {suffix!r}; supported: {list(MESH_SUFFIXES)}")
    check_inside(path, roots, "mesh file")
    if suffix == ".gltf" and roots is not None:
        _check_gltf_references(path, roots)
    try:
        # OBJ: one object per ``o`` directive (trimesh merges them by material otherwise).
        options: dict[str, Any] = {"split_objects": True} if suffix == ".obj" else {}
        return trimesh.load_scene(str(path), process=False, **options)
    except Exception as exc:  # trimesh raises many types on malformed files
        raise SceneError(f"cannot read mesh file {str(path)!r}: {type(exc).__name__}: {exc}") from exc


def node_meshes(tscene: trimesh.Scene) -> list[tuple[str, trimesh.Trimesh]]:
    """Each triangle-carrying node of ``tscene`` as ``(node name, mesh in the scene frame)``.

    Nodes are sorted by name; the meshes are copies with the node transform applied and
    material-only visuals turned into plain colours (see :func:`normalize_visual`).
    """
    out = []
    for node in sorted(tscene.graph.nodes_geometry):
        transform, geometry_name = tscene.graph[node]
        geometry = tscene.geometry[geometry_name]
        if not isinstance(geometry, trimesh.Trimesh) or len(geometry.faces) == 0:
            continue
        mesh = geometry.copy()
        mesh.apply_transform(transform)
        normalize_visual(mesh)
        out.append((str(node), mesh))
    return out


def normalize_visual(mesh: trimesh.Trimesh) -> None:
    """Replace a texture visual that has no image (a flat material colour) by face colours.

    glTF materials without a texture load as ``TextureVisuals`` with only a base colour; plain
    colours are what the raycast renderer and the PLY writer understand, and they lose nothing here.
    """
    visual = mesh.visual
    if isinstance(visual, trimesh.visual.TextureVisuals) and (visual.uv is None or _material_image(visual.material) is None):
        color = np.asarray(visual.material.main_color, dtype=np.uint8)
        mesh.visual = trimesh.visual.ColorVisuals(mesh, face_colors=np.tile(color, (len(mesh.faces), 1)))


def load_mesh_file(path: Path, up_axis: str | None = None, roots: Sequence[Path] | None = None) -> Scene:
    """Load a glb/gltf/obj/ply/stl file as a z-up :class:`Scene`, one object per node.

    Args:
        path: the mesh file.
        up_axis: ``"y"`` or ``"z"``, the file's up axis; None takes the format's default
            (:func:`default_up_axis`).
        roots: resolved scene roots every file read must lie in; None for no check.

    Returns:
        A Scene named after the file stem; bounds are the meshes' bounding box; metadata has
        ``kind="mesh"``, ``source`` and ``up_axis``.
    """
    up = default_up_axis(path) if up_axis is None else up_axis
    if up not in UP_AXES:
        raise SceneError(f"up_axis={up_axis!r} is not supported; use one of {list(UP_AXES)} (or None for the format default)")
    parts = node_meshes(read_trimesh_scene(path, roots))
    if not parts:
        raise SceneError(f"mesh file {str(path)!r} contains no triangles")
    objects = []
    for object_id, (name, mesh) in enumerate(parts, start=1):
        if up == "y":
            mesh.apply_transform(Y_UP_TO_Z_UP)
        objects.append(SceneObject(name=name, object_id=object_id, mesh=mesh))
    bounds = objects_bounds(objects)
    extent = float((bounds[1] - bounds[0]).max())
    if extent > LARGE_EXTENT_M:  # legal, but a mesh in millimetres or centimetres looks like this
        log.warning("mesh file %r spans %.0f m; scene units are metres (a mesh in millimetres must be scaled)",
                    str(path), extent)
    return Scene(
        name=path.stem,
        objects=objects,
        bounds=bounds,
        metadata={"kind": "mesh", "source": path.name, "up_axis": up},
    )


LARGE_EXTENT_M = 2000.0
"""A mesh file larger than this along some axis is loaded with a warning about its units."""


def objects_bounds(objects: Sequence[SceneObject]) -> np.ndarray:
    """The axis-aligned box ``(2, 3)`` around every object's vertices."""
    vertices = np.concatenate([o.mesh.vertices for o in objects])
    return np.stack([vertices.min(axis=0), vertices.max(axis=0)])


def _material_image(material) -> object | None:
    return getattr(material, "baseColorTexture", None) or getattr(material, "image", None)


def _check_gltf_references(path: Path, roots: Sequence[Path]) -> None:
    """Refuse a .gltf whose buffers or images point outside the roots."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SceneError(f"cannot read glTF file {str(path)!r}: {exc}") from exc
    for entry in doc.get("buffers", []) + doc.get("images", []):
        uri = entry.get("uri") if isinstance(entry, dict) else None
        if isinstance(uri, str) and not uri.startswith("data:"):
            check_inside(path.parent / unquote(uri), roots, f"file referenced by {path.name}")
