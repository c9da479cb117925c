"""Habitat scenes: ``*.scene_instance.json`` composing a stage and object instances.

Read the way habitat-sim reads them (ReplicaCAD, HSSD, HM3D layouts; see docs/SCENES.md):

- ``<name>.scene_instance.json``: ``stage_instance`` ``{template_name}`` and ``object_instances``
  ``[{template_name, translation, rotation (wxyz), non_uniform_scale, uniform_scale,
  translation_origin ("COM" | "asset_local", any case), motion_type}]``.
- ``*.scene_dataset_config.json`` (in the scene file's directory or up to three levels above it,
  or given explicitly) defines the templates, per section ``stages`` / ``objects``:
  ``default_attributes`` (applied under every template of the section); ``configs[]`` inline
  entries ``{original_file, template_handle, attributes}`` (``original_file`` a config JSON or a
  mesh, ``attributes`` overriding it); and ``paths`` ``{".json": [dirs, files or globs]}`` of
  ``*.stage_config.json`` / ``*.object_config.json`` files (``".glb"`` and the other mesh suffixes:
  mesh files, each its own template). A template name matches a handle
  exactly, as a path suffix, or by file name, else the first handle (sorted) that contains it, as
  habitat-sim's substring lookup (``getFullAttrNameFromStr``) does. Not defined
  there, ``<template>.<kind>_config.json`` is searched for under the dataset directory, and a
  template that names a mesh file is its own render asset.
- A template's ``render_asset`` (relative to its config file) with ``scale``, ``up`` / ``front``
  (the asset's frame; default y-up, -z front) and ``COM``.

Placement, as habitat-sim does it (y-up frame): the asset is reoriented (``up``/``front`` to +y/-z),
THEN scaled by ``S = config scale * uniform_scale * non_uniform_scale``; an object instance is
``world = translation + R(rotation) @ (S @ v' - S @ origin)`` with ``v'`` the reoriented vertex and
``origin`` the config's ``COM`` (else the reoriented asset's bounding-box centre) for
``translation_origin="com"`` and zero for ``"asset_local"``. Instances default to the scene's
top-level ``translation_origin``, and to COM when that is absent or COM. The stage is scaled only:
habitat-sim ignores the stage instance's translation and rotation. The composed scene is turned from
Habitat's y-up to our z-up (+90 deg about x). All objects are static; ``motion_type`` is ignored.
Articulated objects are not loaded (their count is in ``metadata["skipped_articulated"]``).

Segmentation ids: the stage is 1, object instances are 2, 3, ... in file order.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any, Sequence, cast

import numpy as np
import trimesh

from visfly_dist.errors import SceneError
from visfly_dist.scenes.meshes import MESH_SUFFIXES, Y_UP_TO_Z_UP, node_meshes, objects_bounds, read_trimesh_scene
from visfly_dist.scenes.paths import check_inside, is_inside
from visfly_dist.scenes.scene import Scene, SceneObject

SCENE_INSTANCE_SUFFIX = ".scene_instance.json"
DATASET_CONFIG_SUFFIX = ".scene_dataset_config.json"
TRANSLATION_ORIGINS = ("com", "asset_local")
KINDS = ("stage", "object")
_HABITAT_UP = np.array([0.0, 1.0, 0.0])
_HABITAT_FRONT = np.array([0.0, 0.0, -1.0])
_ORTHOGONAL_TOLERANCE = 1e-3


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
    default_origin = _origin(instance.get("translation_origin", "com"), "the scene's top-level translation_origin")

    objects: list[SceneObject] = []
    stage = instance.get("stage_instance")
    if stage is not None:
        asset = dataset.asset(stage, "stage")
        mesh = _placed(asset, stage, stage_instance=True, origin="asset_local")
        objects.append(SceneObject(name="stage", object_id=1, mesh=mesh))
    for index, entry in enumerate(instance.get("object_instances", [])):
        asset = dataset.asset(entry, "object")
        origin = _origin(entry.get("translation_origin", default_origin), f"translation_origin of {entry['template_name']!r}")
        mesh = _placed(asset, entry, stage_instance=False, origin=origin)
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


@dataclass
class _Template:
    """One stage/object template: its merged attributes and where its relative paths start."""

    handle: str
    attributes: dict
    base: Path
    origin: str        # where it was defined, for error messages


@dataclass
class _Asset:
    """A render asset reoriented to Habitat's frame (unscaled), its config scale and COM."""

    mesh: trimesh.Trimesh
    scale: np.ndarray
    com: np.ndarray


class _Dataset:
    """The stage/object templates of one dataset, and their render assets (cached)."""

    def __init__(self, config_path: Path | None, config: dict, fallback_dir: Path, roots: Sequence[Path] | None) -> None:
        self.dir = config_path.parent if config_path else fallback_dir
        self.name = config_path.name if config_path else None
        self.config = config
        self.roots = roots
        self._templates: dict[str, list[_Template]] = {}
        self._cache: dict[tuple[str, str], _Asset] = {}

    def asset(self, entry: Any, kind: str) -> _Asset:
        if not isinstance(entry, dict) or not isinstance(entry.get("template_name"), str):
            raise SceneError(f"Habitat {kind} instance {entry!r} needs a string 'template_name'")
        key = (kind, entry["template_name"])
        if key not in self._cache:
            self._cache[key] = self._load(*key)
        cached = self._cache[key]
        return _Asset(cached.mesh.copy(), cached.scale, cached.com)

    def _load(self, kind: str, name: str) -> _Asset:
        template = self._find(kind, name)
        if template is None:
            direct = self.dir / name
            if direct.suffix.lower() in MESH_SUFFIXES and direct.is_file():
                template = _Template(name, {**self._defaults(kind), "render_asset": name}, self.dir, "its own mesh file")
            else:
                where = f"dataset config {self.name!r}" if self.name else "no dataset config found"
                raise SceneError(
                    f"Habitat {kind} template {name!r}: no {Path(name).name}.{kind}_config.json and no matching "
                    f"inline {kind}s.configs[] entry ({where}; searched the inline definitions, the {kind}s "
                    f"paths, then every file under {str(self.dir)!r}), and no mesh file of that name"
                )
        render_asset = template.attributes.get("render_asset")
        if not isinstance(render_asset, str):
            raise SceneError(f"Habitat {kind} template {template.handle!r} ({template.origin}) has no 'render_asset' "
                             f"mesh path (got {render_asset!r})")
        candidates = [template.base / render_asset, self.dir / render_asset]
        mesh_path = next((c for c in candidates if c.is_file()), candidates[0])
        mesh = self._read_mesh(mesh_path)
        try:
            return _reframe(mesh, template.attributes)
        except (TypeError, ValueError) as exc:
            raise SceneError(f"Habitat {kind} template {template.handle!r} ({template.origin}): bad "
                             f"scale/up/front/COM: {exc}") from exc

    def _defaults(self, kind: str) -> dict:
        defaults = self._section(kind).get("default_attributes", {})
        return dict(defaults) if isinstance(defaults, dict) else {}

    def _section(self, kind: str) -> dict:
        section = self.config.get(f"{kind}s", {})
        return section if isinstance(section, dict) else {}

    def _find(self, kind: str, name: str) -> _Template | None:
        """The template best matching ``name``: exact handle, then path suffix, then file name, then
        the first handle (sorted) that holds ``name`` as a substring."""
        if kind not in self._templates:
            self._templates[kind] = self._inline(kind) + self._from_paths(kind)
        best, best_score = None, 0
        for template in self._templates[kind]:
            score = _match_score(template.handle, name, kind)
            if score > best_score:
                best, best_score = template, score
        if best is not None:
            return best
        # habitat-sim's getFullAttrNameFromStr: else the first handle (sorted) holding the name
        key = _handle(name, kind)
        holding = sorted((t for t in self._templates[kind] if key and key in t.handle), key=lambda t: t.handle)
        if holding:
            return holding[0]
        fallback = [self.dir / f"{name}.{kind}_config.json"]
        fallback.extend(sorted(self.dir.rglob(f"{Path(name).name}.{kind}_config.json")))
        for candidate in fallback:
            if candidate.is_file() and self._allowed(candidate):
                return self._file_template(kind, candidate)
        return None

    def _inline(self, kind: str) -> list[_Template]:
        """Templates of ``<kind>s.configs[]``: an original file (config or mesh) with overrides."""
        configs = self._section(kind).get("configs", [])
        if not isinstance(configs, list):
            raise SceneError(f"{self.name!r}: {kind}s.configs must be a list of {{original_file, attributes}} entries")
        out = []
        for i, cell in enumerate(configs):
            where = f"inline {kind}s.configs[{i}] of {self.name!r}"
            if not isinstance(cell, dict):
                raise SceneError(f"{where} must be an object with original_file and/or template_handle and attributes")
            original, handle = cell.get("original_file"), cell.get("template_handle")
            overrides = cell.get("attributes", {})
            if not isinstance(overrides, dict) or not isinstance(original or handle, str):
                raise SceneError(f"{where} needs a string 'original_file' or 'template_handle' and an object 'attributes'")
            attributes, base = self._defaults(kind), self.dir
            if isinstance(original, str):
                original_path = self.dir / original
                if original_path.suffix.lower() in MESH_SUFFIXES:
                    attributes["render_asset"] = original
                elif original_path.is_file():
                    attributes.update(_read_json(original_path, self.roots))
                    base = original_path.parent
                else:
                    raise SceneError(f"{where}: original_file {original!r} does not exist under {str(self.dir)!r}")
            attributes.update(overrides)
            out.append(_Template(_handle(handle if isinstance(handle, str) else str(original), kind), attributes, base, where))
        return out

    def _from_paths(self, kind: str) -> list[_Template]:
        """Templates from the section's ``paths``: the config files its ``.json`` entries list, and
        the mesh files its mesh-suffix entries (``".glb": [...]``) list, each its own render asset."""
        paths = self._section(kind).get("paths", {})
        out: list[_Template] = []
        for key, patterns in (paths.items() if isinstance(paths, dict) else []):
            key = str(key).lower()
            if key != ".json" and key not in MESH_SUFFIXES:
                continue
            suffix = f".{kind}_config.json" if key == ".json" else key
            files: list[Path] = []
            for pattern in patterns if isinstance(patterns, list) else []:
                found = sorted(self.dir.glob(pattern)) if any(c in pattern for c in "*?[") else [self.dir / pattern]
                for item in found:
                    if item.is_dir():
                        files.extend(sorted(item.glob(f"*{suffix}")))
                    elif item.is_file() and item.name.lower().endswith(suffix):
                        files.append(item)
            for f in dict.fromkeys(files):
                if not self._allowed(f):
                    continue
                if key == ".json":
                    out.append(self._file_template(kind, f))
                else:
                    relative = f.relative_to(self.dir).as_posix() if f.is_relative_to(self.dir) else f.name
                    out.append(_Template(_handle(relative, kind), {**self._defaults(kind), "render_asset": relative},
                                         self.dir, str(f)))
        return out

    def _file_template(self, kind: str, path: Path) -> _Template:
        handle = _handle(path.relative_to(self.dir).as_posix() if path.is_relative_to(self.dir) else path.name, kind)
        return _Template(handle, {**self._defaults(kind), **_read_json(path, self.roots)}, path.parent, str(path))

    def _allowed(self, path: Path) -> bool:
        return self.roots is None or is_inside(path, self.roots)

    def _read_mesh(self, path: Path) -> trimesh.Trimesh:
        if not path.is_file():
            raise SceneError(f"Habitat render asset {str(path)!r} does not exist")
        parts = node_meshes(read_trimesh_scene(path, self.roots))
        if not parts:
            raise SceneError(f"Habitat render asset {str(path)!r} contains no triangles")
        # concatenate is typed Geometry: meshes make a mesh
        return parts[0][1] if len(parts) == 1 else cast(trimesh.Trimesh, trimesh.util.concatenate([m for _, m in parts]))


def _handle(text: str, kind: str) -> str:
    """A template handle without the config or mesh suffix, as a posix path."""
    for suffix in (f".{kind}_config.json", ".json", *MESH_SUFFIXES):
        if text.lower().endswith(suffix):
            return text[: -len(suffix)]
    return text


def _match_score(handle: str, name: str, kind: str) -> int:
    """3: same handle; 2: ``name`` is a path suffix of it; 1: same file name; 0: no match."""
    name = _handle(name, kind)
    if handle == name:
        return 3
    if handle.endswith("/" + name.lstrip("./")):
        return 2
    return int(PurePosixPath(handle).name == PurePosixPath(name).name)


def _reframe(mesh: trimesh.Trimesh, attributes: dict) -> _Asset:
    """Reorient the mesh from its ``up``/``front`` frame to Habitat's; return it with scale and COM."""
    scale = _vector(attributes.get("scale", (1.0, 1.0, 1.0)), "scale")
    up = _vector(attributes.get("up", _HABITAT_UP), "up")
    front = _vector(attributes.get("front", _HABITAT_FRONT), "front")
    transform = np.eye(4)
    transform[:3, :3] = frame_rotation(up, front)
    mesh.apply_transform(transform)
    com = attributes.get("COM")
    com = mesh.bounds.mean(axis=0) if com is None else _vector(com, "COM")
    return _Asset(mesh, scale, com)


def frame_rotation(up: np.ndarray, front: np.ndarray) -> np.ndarray:
    """Rotation ``(3, 3)`` taking an asset's ``up``/``front`` to Habitat's +y / -z.

    Raises:
        ValueError: a zero vector, or ``up`` and ``front`` not orthogonal (habitat-sim refuses those too).
    """
    norms = np.linalg.norm(up), np.linalg.norm(front)
    if min(norms) < 1e-9:
        raise ValueError(f"up={up.tolist()} and front={front.tolist()} must be non-zero")
    if abs(up @ front) / (norms[0] * norms[1]) > _ORTHOGONAL_TOLERANCE:
        raise ValueError(f"up={up.tolist()} and front={front.tolist()} must be orthogonal")

    def basis(u: np.ndarray, f: np.ndarray) -> np.ndarray:
        u, f = u / np.linalg.norm(u), f / np.linalg.norm(f)
        return np.stack([f, u, np.cross(f, u)], axis=1)

    return basis(_HABITAT_UP, _HABITAT_FRONT) @ basis(up, front).T


def _placed(asset: _Asset, entry: dict, stage_instance: bool, origin: str) -> trimesh.Trimesh:
    """The instance transform (module docstring) applied to the asset's mesh, in Habitat's frame."""
    try:
        scale = asset.scale * _vector(entry.get("non_uniform_scale", (1.0, 1.0, 1.0)), "non_uniform_scale")
        scale = scale * float(entry.get("uniform_scale", 1.0))
        shift = asset.com if origin == "com" else np.zeros(3)
        transform = np.diag([*scale, 1.0]) @ trimesh.transformations.translation_matrix(-shift)
        if not stage_instance:   # habitat-sim ignores the stage instance's translation and rotation
            quaternion = np.asarray(entry.get("rotation", (1.0, 0.0, 0.0, 0.0)), dtype=np.float64).reshape(4)
            if not np.linalg.norm(quaternion) > 0:
                raise ValueError(f"rotation {quaternion.tolist()} is not a quaternion")
            rotation = trimesh.transformations.quaternion_matrix(quaternion)
            translation = _vector(entry.get("translation", (0.0, 0.0, 0.0)), "translation")
            transform = trimesh.transformations.translation_matrix(translation) @ rotation @ transform
        if not np.all(np.isfinite(transform)):
            raise ValueError("values must be finite")
    except (TypeError, ValueError) as exc:
        raise SceneError(
            f"Habitat instance of {entry.get('template_name')!r} has a bad translation/rotation/scale: {exc}; "
            "expected translation [x, y, z], rotation [w, x, y, z], non_uniform_scale [sx, sy, sz], uniform_scale s"
        ) from exc
    asset.mesh.apply_transform(transform)
    return asset.mesh


def _origin(value: Any, what: str) -> str:
    """A ``translation_origin`` value, lower-cased (habitat-sim reads it case-insensitively)."""
    if not isinstance(value, str) or value.lower() not in TRANSLATION_ORIGINS:
        raise SceneError(f"{what}={value!r} is not supported; use one of {list(TRANSLATION_ORIGINS)} (any case)")
    return value.lower()


def _vector(value: Any, name: str) -> np.ndarray:
    vector = np.asarray(value, dtype=np.float64).reshape(-1)
    if vector.shape != (3,) or not np.all(np.isfinite(vector)):
        raise ValueError(f"{name}={value!r} must be 3 finite numbers")
    return vector


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
