"""Habitat transform rules against transforms computed independently here, on synthetic datasets.

Each dataset exercises one form real datasets use: inline ``configs[]`` templates, ``paths`` globs,
lowercase ``com``, config scale with an explicit COM, non-uniform scale after an up/front
reorientation, a z-up asset, and a stage instance translation (ignored, as habitat-sim does).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from visfly_dist.errors import SceneError
from visfly_dist.scenes import load_scene

# An asymmetric tetrahedron (no symmetry can hide a wrong rotation or scale), authored y-up.
TETRA = trimesh.Trimesh([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 3.0]],
                        [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], process=False)


def _write_json(path: Path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))


def _raw_vertices(path: Path) -> np.ndarray:
    """The asset's vertices as stored in the file (one mesh)."""
    (mesh,) = trimesh.load_scene(str(path), process=False).geometry.values()
    return np.asarray(mesh.vertices, dtype=np.float64)


def _to_z_up(v: np.ndarray) -> np.ndarray:
    """Habitat (y-up) -> ours (z-up): (x, y, z) -> (x, -z, y)."""
    return np.stack([v[:, 0], -v[:, 2], v[:, 1]], axis=1)


def _quat_rotate(q, v: np.ndarray) -> np.ndarray:
    """Rotate rows of ``v`` by the unit quaternion ``q`` (w, x, y, z): v + 2 r x (r x v + w v)."""
    w, r = q[0], np.asarray(q[1:], dtype=np.float64)
    return v + 2.0 * np.cross(r, np.cross(r, v) + w * v)


@pytest.fixture
def root(tmp_path) -> Path:
    root = tmp_path / "ds"
    (root / "assets").mkdir(parents=True)
    TETRA.export(root / "assets" / "tetra.glb")
    room = trimesh.creation.box((8.0, 3.0, 6.0), transform=trimesh.transformations.translation_matrix([0, 1.5, 0]))
    room.export(root / "assets" / "room.glb")
    return root


def _scene(root: Path, instance: dict, dataset: dict):
    _write_json(root / "ds.scene_dataset_config.json", dataset)
    _write_json(root / "scenes" / "s.scene_instance.json", instance)
    return load_scene(root / "scenes" / "s.scene_instance.json")


def test_inline_templates_with_original_file_and_attribute_overrides(root):
    _write_json(root / "configs" / "tetra.object_config.json", {"render_asset": "../assets/tetra.glb", "scale": [5, 5, 5]})
    dataset = {
        "stages": {"configs": [{"original_file": "assets/room.glb", "template_handle": "rooms/main", "attributes": {}}]},
        "objects": {"configs": [{"original_file": "configs/tetra.object_config.json",
                                 "attributes": {"scale": [2.0, 1.0, 1.0]}}]},
    }
    instance = {"stage_instance": {"template_name": "main"},
                "object_instances": [{"template_name": "tetra", "translation": [1, 2, 3], "translation_origin": "asset_local"}]}
    scene = _scene(root, instance, dataset)
    raw = _raw_vertices(root / "assets" / "tetra.glb")
    expected = _to_z_up(raw * [2.0, 1.0, 1.0] + [1, 2, 3])       # the override wins over the file's scale
    np.testing.assert_allclose(scene.object_by_id(2).mesh.vertices, expected, atol=1e-9)
    np.testing.assert_allclose(scene.bounds, [[-4, -3, 0], [4, 3, 3]], atol=1e-9)


def test_paths_globs_and_lowercase_com_with_config_scale_and_com(root):
    _write_json(root / "objects" / "a" / "tetra.object_config.json",
                {"render_asset": "../../assets/tetra.glb", "scale": [2.0, 3.0, 0.5], "COM": [0.1, 0.2, 0.3]})
    dataset = {"objects": {"paths": {".json": ["objects/*"]}}}
    s = math.sqrt(0.5)
    q = [s, 0.0, s, 0.0]
    instance = {"object_instances": [{"template_name": "tetra", "translation": [1, -1, 2], "rotation": q,
                                      "translation_origin": "com", "uniform_scale": 2.0,
                                      "non_uniform_scale": [1.0, 0.5, 1.0]}]}
    scene = _scene(root, instance, dataset)
    raw = _raw_vertices(root / "assets" / "tetra.glb")
    scale = np.array([2.0, 3.0, 0.5]) * 2.0 * np.array([1.0, 0.5, 1.0])
    local = scale * raw - scale * np.array([0.1, 0.2, 0.3])          # habitat-sim: COM shift = scale * -COM
    expected = _to_z_up(_quat_rotate(q, local) + [1, -1, 2])
    np.testing.assert_allclose(scene.object_by_id(2).mesh.vertices, expected, atol=1e-9)
    assert scene.metadata["num_objects"] == 1 and scene.bounds.shape == (2, 3)


def test_bounding_box_com_and_scene_level_asset_local(root):
    _write_json(root / "c" / "tetra.object_config.json", {"render_asset": "../assets/tetra.glb", "scale": [3.0, 1.0, 1.0]})
    dataset = {"objects": {"paths": {".json": ["c"]}}}
    raw = _raw_vertices(root / "assets" / "tetra.glb")
    centre = (raw.min(axis=0) + raw.max(axis=0)) / 2
    instance = {"object_instances": [{"template_name": "tetra", "translation": [0, 5, 0]},
                                     {"template_name": "tetra", "translation": [0, 5, 0], "translation_origin": "AsSeT_LoCaL"}]}
    scene = _scene(root, instance, dataset)
    expected_com = _to_z_up((raw - centre) * [3.0, 1.0, 1.0] + [0, 5, 0])
    np.testing.assert_allclose(scene.object_by_id(2).mesh.vertices, expected_com, atol=1e-9)
    np.testing.assert_allclose(scene.object_by_id(3).mesh.vertices, _to_z_up(raw * [3.0, 1.0, 1.0] + [0, 5, 0]), atol=1e-9)
    instance["translation_origin"] = "asset_local"   # the scene-level default
    del instance["object_instances"][1]
    scene = _scene(root, instance, dataset)
    np.testing.assert_allclose(scene.object_by_id(2).mesh.vertices, _to_z_up(raw * [3.0, 1.0, 1.0] + [0, 5, 0]), atol=1e-9)


def test_non_uniform_scale_applies_after_the_up_front_reorientation(root):
    _write_json(root / "o" / "tetra.object_config.json",
                {"render_asset": "../assets/tetra.glb", "up": [0, 0, 1], "front": [0, 1, 0], "scale": [1.0, 2.0, 3.0]})
    dataset = {"objects": {"paths": {".json": ["o/*.object_config.json"]}}}
    instance = {"object_instances": [{"template_name": "tetra", "translation_origin": "asset_local"}]}
    scene = _scene(root, instance, dataset)
    raw = _raw_vertices(root / "assets" / "tetra.glb")
    # z-up, y-front asset -> Habitat: asset up (z) becomes +y, asset front (y) becomes -z.
    reoriented = np.stack([raw[:, 0], raw[:, 2], -raw[:, 1]], axis=1)
    expected = _to_z_up(reoriented * [1.0, 2.0, 3.0])
    np.testing.assert_allclose(scene.object_by_id(2).mesh.vertices, expected, atol=1e-9)
    # A z-up asset lands with its authored z as our z: the tetra's 3 m edge points up, scaled by 2.
    assert scene.object_by_id(2).mesh.bounds[1, 2] == pytest.approx(6.0)


def test_default_attributes_give_a_z_up_stage_and_its_translation_is_ignored(root):
    trimesh.creation.box((8.0, 6.0, 3.0), transform=trimesh.transformations.translation_matrix([0, 0, 1.5])).export(
        root / "assets" / "zroom.glb")
    dataset = {"stages": {"default_attributes": {"up": [0, 0, 1], "front": [0, 1, 0]},
                          "configs": [{"original_file": "assets/zroom.glb", "attributes": {"scale": [2, 2, 2]}}]}}
    instance = {"stage_instance": {"template_name": "zroom", "translation": [5, 5, 5], "rotation": [0, 1, 0, 0],
                                   "uniform_scale": 0.5}}
    scene = _scene(root, instance, dataset)
    np.testing.assert_allclose(scene.bounds, [[-4, -3, 0], [4, 3, 3]], atol=1e-9)


def test_missing_template_error_mentions_inline_definitions(root):
    dataset = {"objects": {"configs": [{"original_file": "assets/tetra.glb", "attributes": {}}]}}
    with pytest.raises(SceneError, match=r"template 'sofa'.*inline objects\.configs\[\] entry.*ds\.scene_dataset_config"):
        _scene(root, {"object_instances": [{"template_name": "sofa"}]}, dataset)
    with pytest.raises(SceneError, match=r"translation_origin of 'tetra'='middle' is not supported.*'com', 'asset_local'"):
        _scene(root, {"object_instances": [{"template_name": "tetra", "translation_origin": "middle"}]}, dataset)
    dataset["objects"]["configs"][0]["attributes"] = {"up": [0, 1, 0], "front": [0, 1, 1]}
    with pytest.raises(SceneError, match=r"inline objects\.configs\[0\].*must be orthogonal"):
        _scene(root, {"object_instances": [{"template_name": "tetra"}]}, dataset)
