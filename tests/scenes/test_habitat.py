"""Habitat scene_instance.json loading on a small synthetic dataset laid out like real ones."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from visfly_dist.errors import SceneError
from visfly_dist.scenes import load_scene, resolve_source


def _box(extents, center, color) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(center))
    mesh.visual.face_colors = [*color, 255]
    return mesh


def _write_json(path: Path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))


@pytest.fixture
def dataset(tmp_path) -> Path:
    """Habitat frame (y-up) assets: a room stage of two slabs, a chair, and a z-up lamp."""
    root = tmp_path / "mini"
    (root / "assets").mkdir(parents=True)
    room = trimesh.Scene()
    room.add_geometry(_box((10, 0.2, 10), (0, -0.1, 0), (90, 90, 90)), node_name="floor")
    room.add_geometry(_box((10, 0.2, 10), (0, 3.1, 0), (200, 200, 200)), node_name="ceiling")
    room.export(root / "assets" / "room.glb")
    _box((0.5, 1.0, 0.5), (0, 0.5, 0), (255, 0, 0)).export(root / "assets" / "chair.glb")  # origin at its feet
    _box((0.2, 0.2, 1.0), (0, 0, 0.5), (0, 0, 255)).export(root / "assets" / "lamp.glb")  # authored z-up

    _write_json(root / "mini.scene_dataset_config.json", {
        "stages": {"paths": {".json": ["configs/stages"]}},
        "objects": {"paths": {".json": ["configs/objects/*"]}},
    })
    _write_json(root / "configs/stages/room.stage_config.json", {"render_asset": "../../assets/room.glb"})
    _write_json(root / "configs/objects/furniture/chair.object_config.json", {"render_asset": "../../../assets/chair.glb"})
    # Not under the listed paths: found by searching the dataset directory.
    _write_json(root / "elsewhere/lamp.object_config.json",
                {"render_asset": "../assets/lamp.glb", "up": [0, 0, 1], "front": [0, 1, 0]})
    s = math.sqrt(0.5)
    _write_json(root / "scenes/apt.scene_instance.json", {
        "stage_instance": {"template_name": "stages/room"},
        "object_instances": [
            {"template_name": "chair", "translation": [1, 2, 0], "rotation": [1, 0, 0, 0],
             "translation_origin": "asset_local", "motion_type": "STATIC"},
            {"template_name": "chair", "translation": [0, 1, -3], "rotation": [s, 0, s, 0],
             "non_uniform_scale": [2, 1, 1], "translation_origin": "COM", "motion_type": "DYNAMIC"},
            {"template_name": "lamp", "translation": [-2, 0, 2], "uniform_scale": 2},
        ],
    })
    return root


def _center_and_extents(mesh):
    return mesh.bounds.mean(axis=0), mesh.bounds[1] - mesh.bounds[0]


def test_habitat_scene_lands_z_up_with_identities(dataset):
    scene = load_scene(dataset / "scenes/apt.scene_instance.json")
    assert [(o.name, o.object_id) for o in scene.objects] == [("stage", 1), ("chair#0", 2), ("chair#1", 3), ("lamp#2", 4)]
    assert scene.name == "apt"
    assert scene.metadata["kind"] == "habitat" and scene.metadata["dataset_config"] == "mini.scene_dataset_config.json"
    np.testing.assert_allclose(scene.bounds, [[-5, -5, -0.2], [5, 5, 3.2]], atol=1e-6)  # the stage's box, z-up

    # asset_local: the chair's feet at Habitat (1, 2, 0) -> z-up (1, 0, 2); its top 1 m higher.
    center, extents = _center_and_extents(scene.object_by_id(2).mesh)
    np.testing.assert_allclose(center, [1, 0, 2.5], atol=1e-6)
    np.testing.assert_allclose(extents, [0.5, 0.5, 1.0], atol=1e-6)
    # COM origin, scaled 2x along its x, then turned 90 deg about Habitat's up: its long side along
    # Habitat z, which is our -y; centre at Habitat (0, 1, -3) -> z-up (0, 3, 1).
    center, extents = _center_and_extents(scene.object_by_id(3).mesh)
    np.testing.assert_allclose(center, [0, 3, 1], atol=1e-6)
    np.testing.assert_allclose(extents, [0.5, 1.0, 1.0], atol=1e-6)
    # A z-up asset (config up/front) stands upright; COM at Habitat (-2, 0, 2) -> z-up (-2, -2, 0).
    center, extents = _center_and_extents(scene.object_by_id(4).mesh)
    np.testing.assert_allclose(center, [-2, -2, 0], atol=1e-6)
    np.testing.assert_allclose(extents, [0.4, 0.4, 2.0], atol=1e-6)

    assert tuple(scene.object_by_id(2).mesh.visual.face_colors[0, :3]) == (255, 0, 0)
    stage_colors = {tuple(c[:3]) for c in scene.object_by_id(1).mesh.visual.face_colors}
    assert stage_colors == {(90, 90, 90), (200, 200, 200)}


def test_habitat_through_resolve_source_and_confinement(dataset, tmp_path):
    scene = resolve_source("scenes/apt.scene_instance.json", roots=[dataset])
    assert len(scene.objects) == 4
    outside = tmp_path / "outside.glb"
    _box((1, 1, 1), (0, 0, 0), (0, 255, 0)).export(outside)
    _write_json(dataset / "configs/objects/furniture/chair.object_config.json", {"render_asset": str(outside)})
    with pytest.raises(SceneError, match="outside the scene roots"):
        resolve_source("scenes/apt.scene_instance.json", roots=[dataset])


def test_habitat_errors_name_the_instance(dataset):
    instance = dataset / "scenes/apt.scene_instance.json"
    data = json.loads(instance.read_text())
    data["object_instances"].append({"template_name": "sofa", "translation": [0, 0, 0]})
    instance.write_text(json.dumps(data))
    with pytest.raises(SceneError, match=r"template 'sofa': no sofa.object_config.json"):
        load_scene(instance)
    data["object_instances"][-1] = {"template_name": "chair", "translation": [0, 0]}
    instance.write_text(json.dumps(data))
    with pytest.raises(SceneError, match=r"instance of 'chair' has a bad translation/rotation/scale"):
        load_scene(instance)
