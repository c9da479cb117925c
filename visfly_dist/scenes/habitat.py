"""Habitat scenes: ``*.scene_instance.json`` composing a stage and object instances.

The layout read here is the one real datasets ship (ReplicaCAD, HSSD, HM3D):

- ``<name>.scene_instance.json``: ``stage_instance`` ``{template_name}`` and ``object_instances``
  ``[{template_name, translation, rotation (wxyz), non_uniform_scale | uniform_scale,
  translation_origin ("COM" | "asset_local"), motion_type}]``.
- ``*.scene_dataset_config.json``, found in the scene file's directory or up to three levels above
  it (or given explicitly): its ``stages`` / ``objects`` entries list ``paths`` ``{".json": [dirs or
  globs]}`` where ``<template>.stage_config.json`` / ``<template>.object_config.json`` live. A
  template not found there is searched for anywhere under the dataset directory, and a template
  that names a mesh file directly is used as its own render asset.
- A config's ``render_asset`` is a mesh path relative to the config file; optional ``scale``,
  ``up`` / ``front`` (the asset's frame, default y-up, -z front) and ``COM`` are honoured.

Placement (Habitat, y-up): ``world = translation + R(rotation) @ (scale * (v - origin))`` where
``origin`` is the asset's centre of mass for ``translation_origin="COM"`` (the config's ``COM``,
else the asset's bounding-box centre, as Habitat computes it) and zero for ``"asset_local"``. Object
instances default to ``COM`` (the scene's top-level ``translation_origin`` overrides), the stage to
``asset_local``. The composed scene is then turned from Habitat's y-up to our z-up (+90 deg about
x: Habitat +y becomes +z). All objects are static; ``motion_type`` is ignored. Articulated objects
are not loaded (their count is kept in ``metadata["skipped_articulated"]``).

Segmentation ids: the stage is 1, object instances are 2, 3, ... in file order.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import trimesh

from visfly_dist.errors import SceneError
from visfly_dist.scenes.meshes import MESH_SUFFIXES, Y_UP_TO_Z_UP, node_meshes, objects_bounds, read_trimesh_scene
from visfly_dist.scenes.paths import check_inside, is_inside
from visfly_dist.scenes.scene import Scene, SceneObject

SCENE_INSTANCE_SUFFIX = ".scene_instance.json"
DATASET_CONFIG_SUFFIX = ".scene_dataset_config.json"
TRANSLATION_ORIGINS = ("COM", "asset_local")
_HABITAT_UP = np.array([0.0, 1.0, 0.0])
_HABITAT_FRONT = np.array([0.0, 0.0, -1.0])


def load_habitat_scene(
    path: Path, dataset_config: Path | None = None, roots: Sequence[Path] | None = None
) -> Scene:
    """Load a Habitat ``*.scene_instance.json`` as a z-up :class:`Scene`.

    Args:
        path: the scene instance file.
        dataset_config: the ``*.scene_dataset_config.json``; None searches for it (module docstring).
        roots: resolved scene roots every file read must lie in; None for no check.

    Returns:
        Scene with the stage (id 1) and each object instance (ids 2..); bounds are the stage's
        bounding box (all objects' when there is no stage); metadata has ``kind="habitat"``.
    """
    instance = _read_json(path, roots)
    config_path = dataset_config if dataset_config is not None else _find_dataset_config(path, roots)
    dataset = _Dataset(config_path, _read_json(config_path, roots) if config_path else {}, path.parent, roots)
    default_origin = instance.get("translation_origin", "COM")

    objects: list[SceneObject] = []
    stage = instance.get("stage_instance")
    if stage is not None:
        mesh = _place(dataset.asset(stage, "stage"), stage, stage.get("translation_origin", "asset_local"))
        objects.append(SceneObject(name="stage", object_id=1, mesh=mesh))
    for index, entry in enumerate(instance.get("object_instances", [])):
        asset = dataset.asset(entry, "object")
        mesh = _place(asset, entry, entry.get("translation_origin", default_origin))
        name = f"{Path(entry['template_name']).name}#{index}"
        objects.append(SceneObject(name=name, object_id=index + 2, mesh=mesh))
    if not objects:
        raise SceneError(f"Habitat scene {str(path)!r} has neither a stage_instance nor object_instances")
    for obj in objects:
        obj.mesh.apply_transform(Y_UP_TO_Z_UP)
    bounds_from = objects[:1] if stage is not None else objects
    return Scene(
        name=path.name[: -len(SCENE_INSTANCE_SUFFIX)] if path.name.endswith(SCENE_INSTANCE_SUFFIX) else path.stem,
        objects=objects,
        bounds=objects_bounds(bounds_from),
        metadata={
            "kind": "habitat",
            "source": path.name,
            "dataset_config": config_path.name if config_path else None,
            "stage": None if stage is None else str(stage.get("template_name")),
            "num_objects": len(objects) - (stage is not None),
            "skipped_articulated": len(instance.get("articulated_object_instances", [])),
        },
    )


class _Asset:
    """A render asset reframed to Habitat's frame, with its config scale applied."""

    def __init__(self, mesh: trimesh.Trimesh, com: np.ndarray) -> None:
        self.mesh = mesh
        self.com = com


class _Dataset:
    """Finds stage/object configs of one dataset and loads their render assets (cached)."""

    def __init__(self, config_path: Path | None, config: dict, fallback_dir: Path, roots: Sequence[Path] | None) -> None:
        self.dir = config_path.parent if config_path else fallback_dir
        self.config = config
        self.roots = roots
        self._cache: dict[tuple[str, str], _Asset] = {}

    def asset(self, entry: Any, kind: str) -> _Asset:
        if not isinstance(entry, dict) or not isinstance(entry.get("template_name"), str):
            raise SceneError(f"Habitat {kind} instance {entry!r} needs a string 'template_name'")
        key = (kind, entry["template_name"])
        if key not in self._cache:
            self._cache[key] = self._load(*key)
        cached = self._cache[key]
        return _Asset(cached.mesh.copy(), cached.com)

    def _load(self, kind: str, template: str) -> _Asset:
        config_file = self._find_config(kind, template)
        if config_file is None:
            direct = self.dir / template
            if direct.suffix.lower() in MESH_SUFFIXES and direct.is_file():
                return _Asset(*_reframe(self._read_mesh(direct), {}))
            raise SceneError(
                f"Habitat {kind} template {template!r}: no {Path(template).name}.{kind}_config.json under "
                f"{str(self.dir)!r} (searched the dataset config's {kind}s paths, then the whole dataset directory)"
            )
        config = _read_json(config_file, self.roots)
        render_asset = config.get("render_asset")
        if not isinstance(render_asset, str):
            raise SceneError(f"{str(config_file)!r} has no 'render_asset' mesh path (got {render_asset!r})")
        mesh = self._read_mesh(config_file.parent / render_asset)
        try:
            return _Asset(*_reframe(mesh, config))
        except (TypeError, ValueError) as exc:
            raise SceneError(f"{str(config_file)!r}: bad scale/up/front/COM ({exc}); expected 3-vectors, up and front not parallel") from exc

    def _find_config(self, kind: str, template: str) -> Path | None:
        filename = f"{Path(template).name}.{kind}_config.json"
        candidates = []
        for pattern in self.config.get(f"{kind}s", {}).get("paths", {}).get(".json", []):
            for found in sorted(self.dir.glob(pattern)) if any(c in pattern for c in "*?[") else [self.dir / pattern]:
                candidates.append(found if found.name == filename else found / filename)
        candidates.append(self.dir / f"{template}.{kind}_config.json")
        candidates.extend(sorted(self.dir.rglob(filename)))
        for candidate in candidates:
            if candidate.is_file() and (self.roots is None or is_inside(candidate, self.roots)):
                return candidate
        return None

    def _read_mesh(self, path: Path) -> trimesh.Trimesh:
        if not path.is_file():
            raise SceneError(f"Habitat render asset {str(path)!r} does not exist")
        parts = node_meshes(read_trimesh_scene(path, self.roots))
        if not parts:
            raise SceneError(f"Habitat render asset {str(path)!r} contains no triangles")
        return parts[0][1] if len(parts) == 1 else trimesh.util.concatenate([m for _, m in parts])


def _reframe(mesh: trimesh.Trimesh, config: dict) -> tuple[trimesh.Trimesh, np.ndarray]:
    """Apply a config's ``scale`` and ``up``/``front`` frame; return the mesh and its COM."""
    scale = np.asarray(config.get("scale", (1.0, 1.0, 1.0)), dtype=np.float64)
    up = np.asarray(config.get("up", _HABITAT_UP), dtype=np.float64)
    front = np.asarray(config.get("front", _HABITAT_FRONT), dtype=np.float64)
    transform = np.eye(4)
    transform[:3, :3] = _frame_rotation(up, front) @ np.diag(scale.reshape(3))
    if not np.all(np.isfinite(transform)):
        raise ValueError("the asset frame is degenerate")
    mesh.apply_transform(transform)
    com = config.get("COM")
    com = mesh.bounds.mean(axis=0) if com is None else np.asarray(com, dtype=np.float64).reshape(3)
    return mesh, com


def _frame_rotation(up: np.ndarray, front: np.ndarray) -> np.ndarray:
    """Rotation taking the asset's ``up``/``front`` to Habitat's +y / -z."""
    def basis(u: np.ndarray, f: np.ndarray) -> np.ndarray:
        u = u / np.linalg.norm(u)
        f = f - u * (f @ u)
        f = f / np.linalg.norm(f)
        return np.stack([f, u, np.cross(f, u)], axis=1)

    return basis(_HABITAT_UP, _HABITAT_FRONT) @ basis(up, front).T


def _place(asset: _Asset, entry: dict, origin: str) -> trimesh.Trimesh:
    """Instance transform (module docstring) applied to the asset's mesh, in Habitat's frame."""
    if origin not in TRANSLATION_ORIGINS:
        raise SceneError(
            f"translation_origin={origin!r} of {entry.get('template_name')!r} is not supported; use one of {list(TRANSLATION_ORIGINS)}"
        )
    try:
        transform = _instance_transform(entry, -asset.com if origin == "COM" else np.zeros(3))
    except (TypeError, ValueError) as exc:
        raise SceneError(
            f"Habitat instance of {entry.get('template_name')!r} has a bad translation/rotation/scale: {exc}; "
            "expected translation [x, y, z], rotation [w, x, y, z], non_uniform_scale [sx, sy, sz], uniform_scale s"
        ) from exc
    asset.mesh.apply_transform(transform)
    return asset.mesh


def _instance_transform(entry: dict, shift_by: np.ndarray) -> np.ndarray:
    scale = np.asarray(entry.get("non_uniform_scale", (1.0, 1.0, 1.0)), dtype=np.float64).reshape(3)
    scale = scale * float(entry.get("uniform_scale", 1.0))
    rotation = trimesh.transformations.quaternion_matrix(np.asarray(entry.get("rotation", (1.0, 0.0, 0.0, 0.0)), dtype=np.float64).reshape(4))
    translation = np.asarray(entry.get("translation", (0.0, 0.0, 0.0)), dtype=np.float64).reshape(3)
    transform = trimesh.transformations.translation_matrix(translation) @ rotation @ np.diag([*scale, 1.0])
    transform = transform @ trimesh.transformations.translation_matrix(shift_by)
    if not np.all(np.isfinite(transform)):
        raise ValueError("values must be finite")
    return transform


def _find_dataset_config(path: Path, roots: Sequence[Path] | None) -> Path | None:
    directory = path.parent
    for _ in range(4):
        if roots is not None and not is_inside(directory, roots):
            return None
        found = sorted(directory.glob(f"*{DATASET_CONFIG_SUFFIX}"))
        if found:
            return found[0]
        if directory.parent == directory:
            return None
        directory = directory.parent
    return None


def _read_json(path: Path, roots: Sequence[Path] | None) -> dict:
    check_inside(path, roots, "Habitat file")
    try:
        data = json.loads(Path(path).read_text())
    except FileNotFoundError as exc:
        raise SceneError(f"Habitat file {str(path)!r} does not exist") from exc
    except (OSError, ValueError) as exc:
        raise SceneError(f"cannot read Habitat file {str(path)!r}: {exc}") from exc
    if not isinstance(data, dict):
        raise SceneError(f"Habitat file {str(path)!r} must hold a JSON object, got {type(data).__name__}")
    return data
