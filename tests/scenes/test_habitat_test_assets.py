"""A copy of habitat-sim's own test dataset layout (``data/test_assets/dataset_tests/dataset_1``):
its JSON files field for field, with meshes made here. It uses inline ``configs[]`` entries both
with ``original_file`` and with only a ``template_handle`` and a ``render_asset``, section
``default_attributes``, directory globs in ``paths`` (``"stages/*"``), template names that match
a handle by substring (``modified_test_stage``, ``dataset_test_object2``), a top-level
``translation_origin: "com"`` overridden per instance by ``"asset_local"``, and a stage translation
(ignored by habitat-sim)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import trimesh

from visfly_dist.scenes import load_scene

DATASET = {
    "stages": {
        "default_attributes": {"origin": [1.0, 2.0, 3.0]},
        "paths": {".json": ["stages/*"]},
        "configs": [
            {"original_file": "stages/stage_0/dataset_test_stage_0.stage_config.json",
             "template_handle": "modified_test_stage_0",
             "attributes": {"scale": [1, 1, 1], "gravity": [0, -9.8, 0], "margin": 0.041, "friction_coefficient": 0.4,
                            "restitution_coefficient": 0.5, "units_to_meters": 1.0}},
            {"original_file": "stages/stage_1/dataset_test_stage_1.stage_config.json",
             "template_handle": "modified_test_stage_1",
             "attributes": {"scale": [1, 1, 1], "gravity": [0, -9.8, 0], "margin": 0.041, "friction_coefficient": 0.4,
                            "restitution_coefficient": 0.5, "units_to_meters": 1.0}},
            {"template_handle": "new_test_stage",
             "attributes": {"render_asset": "stages/stage_0/dataset_test_stage_0.glb", "up": [0, -1, 0], "scale": [2, 2, 2],
                            "gravity": [0, 9.8, 0], "friction_coefficient": 0.35, "restitution_coefficient": 0.25,
                            "units_to_meters": 2.0, "requires_lighting": False}},
        ],
    },
    "objects": {
        "default_attributes": {"mass": 10.0, "inertia": [3, 2, 1]},
        "paths": {".json": ["objects/*"]},
        "configs": [
            {"original_file": "objects/object_0/dataset_test_object1_0.object_config.json",
             "template_handle": "modified_test_object1_1_slick_heavy",
             "attributes": {"friction_coefficient": 0.2, "mass": 3.5}},
            {"template_handle": "new_test_object3",
             "attributes": {"render_asset": "objects/object_1/dataset_test_object3_1.glb", "friction_coefficient": 0.1,
                            "mass": 1.1}},
        ],
    },
    "light_setups": {"default_attributes": {}, "paths": {".json": ["lights/*"]}, "configs": []},
    "scene_instances": {"paths": {".json": ["scenes/*"]}},
    "navmesh_instances": {"navmesh_path1": "test_navmesh_path1", "navmesh_path2": "test_navmesh_path2"},
    "semantic_scene_descriptor_instances": {"semantic_descriptor_path1": "test_semantic_descriptor_path1",
                                            "semantic_descriptor_path2": "test_semantic_descriptor_path2"},
}
STAGE_CONFIG = {"up": [0, 1, 0], "front": [0, 0, -1], "origin": [0, 0, 0], "scale": [2, 2, 2], "gravity": [0, -9.8, 0],
                "margin": 0.03, "friction_coefficient": 0.3, "restitution_coefficient": 0.3, "units_to_meters": 1.0}
OBJECT1_CONFIG = {"render_asset": "dataset_test_object1_0.glb", "collision_asset": "dataset_test_object1_0.glb",
                  "up": [0.0, 1.0, 0.0], "front": [0.0, 0.0, -1.0], "scale": [1.0, 1.0, 1.0], "margin": 0.03,
                  "friction_coefficient": 0.5, "restitution_coefficient": 0.2, "units_to_meters": 1.0,
                  "force_flat_shading": False, "mass": 0.038, "COM": [0.0, 0.0, 0.0],
                  "use_bounding_box_for_collision": False, "join_collision_meshes": True}
INSTANCE = {
    "translation_origin": "com",
    "stage_instance": {"translation_origin": "asset_local", "template_name": "modified_test_stage",
                       "translation": [1.1, 2.2, 3.3]},
    "object_instances": [
        {"translation_origin": "asset_local", "template_name": "dataset_test_object1", "translation": [0.1, 0.2, 0.3]},
        {"translation_origin": "asset_local", "template_name": "dataset_test_object2", "translation": [0.3, 0.4, 0.5]},
    ],
    "default_lighting": "modified_test_lights", "navmesh_instance": "navmesh_path1",
    "semantic_scene_instance": "semantic_descriptor_path1",
}


def _write(path: Path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))


def _box(path: Path, low, high) -> np.ndarray:
    """A box mesh file (glTF, y-up as stored) and its stored vertices."""
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh = trimesh.creation.box(bounds=[low, high])
    mesh.export(path)
    (stored,) = trimesh.load_scene(str(path), process=False).geometry.values()
    return np.asarray(stored.vertices)


def _z_up(v: np.ndarray) -> np.ndarray:
    return np.stack([v[:, 0], -v[:, 2], v[:, 1]], axis=1)


def test_habitat_sims_own_dataset_1_layout_loads_as_habitat_sim_places_it(tmp_path):
    root = tmp_path / "dataset_1"
    _write(root / "test_dataset_1.scene_dataset_config.json", DATASET)
    stage0 = _box(root / "stages/stage_0/dataset_test_stage_0.glb", [-4, 0, -3], [4, 3, 3])
    _box(root / "stages/stage_1/dataset_test_stage_1.glb", [-9, 0, -9], [9, 1, 9])
    _write(root / "stages/stage_0/dataset_test_stage_0.stage_config.json", {"render_asset": "dataset_test_stage_0.glb", **STAGE_CONFIG})
    _write(root / "stages/stage_1/dataset_test_stage_1.stage_config.json",
           {"render_asset": "dataset_test_stage_1.glb", **STAGE_CONFIG, "requires_lighting": True})
    object1 = _box(root / "objects/object_0/dataset_test_object1_0.glb", [0, 0, 0], [0.2, 0.4, 0.6])
    _write(root / "objects/object_0/dataset_test_object1_0.object_config.json", OBJECT1_CONFIG)
    object2 = _box(root / "objects/object_1/dataset_test_object2_1.glb", [-0.1, 0, -0.1], [0.1, 0.5, 0.1])
    _write(root / "objects/object_1/dataset_test_object2_1.object_config.json",
           {"render_asset": "dataset_test_object2_1.glb", "join_collision_meshes": True})
    _box(root / "objects/object_1/dataset_test_object3_1.glb", [0, 0, 0], [1, 1, 1])
    _write(root / "scenes/scene_0/dataset_test_scene_0.scene_instance.json", INSTANCE)

    scene = load_scene(root / "scenes/scene_0/dataset_test_scene_0.scene_instance.json")
    stage, first, second = scene.objects
    # the stage: the first handle holding "modified_test_stage" (stage_0), its inline scale [1, 1, 1]
    # overriding the file's [2, 2, 2]; the stage instance's translation ignored
    np.testing.assert_allclose(np.sort(stage.mesh.vertices, axis=0), np.sort(_z_up(stage0), axis=0), atol=1e-6)
    # objects placed at their translation from the asset's own origin ("asset_local" beats the
    # top-level "com"); dataset_test_object2 is found by substring through the objects/* glob
    np.testing.assert_allclose(np.sort(first.mesh.vertices, axis=0),
                               np.sort(_z_up(object1 + [0.1, 0.2, 0.3]), axis=0), atol=1e-6)
    np.testing.assert_allclose(np.sort(second.mesh.vertices, axis=0),
                               np.sort(_z_up(object2 + [0.3, 0.4, 0.5]), axis=0), atol=1e-6)


def test_mesh_files_listed_in_paths_are_templates_of_their_own(tmp_path):
    """dataset_0's form: ``"paths": {".json": ["stages"], ".glb": ["stages/stage_test_glbs/*.glb"]}``."""
    root = tmp_path / "dataset_0"
    _write(root / "test_dataset_0.scene_dataset_config.json",
           {"stages": {"default_attributes": {"origin": [1.0, 2.0, 3.0]},
                       "paths": {".json": ["stages"], ".glb": ["stages/stage_test_glbs/*.glb"]}}})
    hall = _box(root / "stages/stage_test_glbs/hall.glb", [-3, 0, -2], [3, 2.5, 2])
    _write(root / "scenes/s.scene_instance.json", {"stage_instance": {"template_name": "hall"}})
    (stage,) = load_scene(root / "scenes/s.scene_instance.json").objects
    np.testing.assert_allclose(np.sort(stage.mesh.vertices, axis=0), np.sort(_z_up(hall), axis=0), atol=1e-6)
