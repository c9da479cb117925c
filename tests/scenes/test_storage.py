"""The visfly scene directory round trip, and loading mesh files (glb, gltf, obj, ply, stl)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from PIL import Image

from visfly_dist.errors import SceneError
from visfly_dist.scenes import GENERATORS, Scene, SceneObject, generate_scene, load_scene, save_scene


def _colored_box(color, center=(0.0, 0.0, 0.0), extents=(1.0, 1.0, 1.0)) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(center))
    mesh.visual.face_colors = [*color, 255]
    return mesh


def _assert_same(a: Scene, b: Scene) -> None:
    assert b.name == a.name and b.metadata == a.metadata
    np.testing.assert_array_equal(b.bounds, a.bounds)
    assert [(o.name, o.object_id) for o in b.objects] == [(o.name, o.object_id) for o in a.objects]
    for x, y in zip(a.objects, b.objects):
        np.testing.assert_array_equal(y.mesh.vertices, x.mesh.vertices)
        np.testing.assert_array_equal(y.mesh.faces, x.mesh.faces)
        np.testing.assert_array_equal(y.mesh.visual.face_colors, x.mesh.visual.face_colors)


@pytest.mark.parametrize("kind", sorted(GENERATORS))
def test_round_trip_every_kind(kind, tmp_path):
    scene = generate_scene(kind, seed=2)
    out = save_scene(scene, tmp_path / kind)
    document = json.loads((out / "scene.json").read_text())
    assert document["format"] == "visfly-scene" and document["version"] == 1
    assert [o["id"] for o in document["objects"]] == [o.object_id for o in scene.objects]
    _assert_same(scene, load_scene(out))
    _assert_same(scene, load_scene(out / "scene.json"))


def test_round_trip_keeps_vertex_colors_and_textures(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=1)
    sphere.vertices = sphere.vertices.astype(np.float32).astype(np.float64)
    sphere.visual.vertex_colors = np.random.default_rng(0).integers(0, 256, (len(sphere.vertices), 4), dtype=np.uint8)
    quad = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    image = Image.fromarray(np.arange(4 * 4 * 3, dtype=np.uint8).reshape(4, 4, 3))
    quad.visual = trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [1, 1], [0, 1]], image=image)
    scene = Scene("mixed", [SceneObject("sphere", 3, sphere), SceneObject("poster", 7, quad)], [[-1, -1, -1], [1, 1, 1]])
    back = load_scene(save_scene(scene, tmp_path / "mixed"))
    assert [(o.name, o.object_id) for o in back.objects] == [("sphere", 3), ("poster", 7)]
    np.testing.assert_array_equal(back.objects[0].mesh.visual.vertex_colors, sphere.visual.vertex_colors)
    np.testing.assert_array_equal(back.objects[0].mesh.vertices, sphere.vertices)
    poster = back.objects[1].mesh
    assert isinstance(poster.visual, trimesh.visual.TextureVisuals)
    np.testing.assert_array_equal(poster.vertices, quad.vertices)  # z-up kept: no glTF conversion
    np.testing.assert_allclose(poster.visual.uv, quad.visual.uv)
    np.testing.assert_array_equal(np.asarray(poster.visual.material.baseColorTexture.convert("RGB")), np.asarray(image))


def test_glb_nodes_become_objects_and_y_up_turns_to_z_up(tmp_path):
    tscene = trimesh.Scene()
    tscene.add_geometry(_colored_box((255, 0, 0)), node_name="b_red", transform=trimesh.transformations.translation_matrix([0, 3, 0]))
    tscene.add_geometry(_colored_box((0, 0, 255)), node_name="a_blue", transform=trimesh.transformations.translation_matrix([2, 0, 1]))
    tscene.export(tmp_path / "two.glb")

    scene = load_scene(tmp_path / "two.glb")
    assert [(o.name, o.object_id) for o in scene.objects] == [("a_blue", 1), ("b_red", 2)]
    red, blue = scene.object_by_id(2).mesh, scene.object_by_id(1).mesh
    np.testing.assert_allclose(red.bounds.mean(axis=0), [0, 0, 3], atol=1e-6)  # glTF +y -> +z
    np.testing.assert_allclose(blue.bounds.mean(axis=0), [2, -1, 0], atol=1e-6)  # glTF +z -> -y
    assert tuple(red.visual.face_colors[0, :3]) == (255, 0, 0)
    np.testing.assert_allclose(scene.bounds, [[-0.5, -1.5, -0.5], [2.5, 0.5, 3.5]], atol=1e-6)
    assert scene.metadata == {"kind": "mesh", "source": "two.glb", "up_axis": "y"}

    as_is = load_scene(tmp_path / "two.glb", up_axis="z")
    np.testing.assert_allclose(as_is.object_by_id(2).mesh.bounds.mean(axis=0), [0, 3, 0], atol=1e-6)
    with pytest.raises(SceneError, match="up_axis='x'"):
        load_scene(tmp_path / "two.glb", up_axis="x")


def test_gltf_with_external_buffer(tmp_path):
    tscene = trimesh.Scene()
    tscene.add_geometry(_colored_box((0, 255, 0)), node_name="green")
    files = trimesh.exchange.gltf.export_gltf(tscene)
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    scene = load_scene(tmp_path / "model.gltf")
    assert [(o.name, o.object_id, len(o.mesh.faces)) for o in scene.objects] == [("green", 1, 12)]


def test_obj_objects_ply_and_stl(tmp_path):
    (tmp_path / "two.obj").write_text(
        "o left\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
        "o right\nv 5 0 0\nv 6 0 0\nv 5 1 0\nv 5 0 1\nf 4 5 6\nf 4 6 7\n"
    )
    obj = load_scene(tmp_path / "two.obj")
    assert [(o.name, o.object_id, len(o.mesh.faces)) for o in obj.objects] == [("left", 1, 1), ("right", 2, 2)]
    np.testing.assert_array_equal(obj.object_by_id(2).mesh.bounds, [[5, 0, 0], [6, 1, 1]])  # z-up as stored

    box = _colored_box((10, 200, 30), center=(1, 2, 3))
    for suffix in ("ply", "stl"):
        box.export(tmp_path / f"box.{suffix}")
        scene = load_scene(tmp_path / f"box.{suffix}")
        assert [o.object_id for o in scene.objects] == [1] and len(scene.objects[0].mesh.faces) == 12
        np.testing.assert_allclose(scene.bounds, [[0.5, 1.5, 2.5], [1.5, 2.5, 3.5]], atol=1e-6)
    ply = load_scene(tmp_path / "box.ply").objects[0].mesh
    assert tuple(ply.visual.face_colors[0, :3]) == (10, 200, 30)


def test_load_errors_name_the_file(tmp_path):
    with pytest.raises(SceneError, match="does not exist"):
        load_scene(tmp_path / "nope.glb")
    with pytest.raises(SceneError, match="has no scene.json"):
        load_scene(tmp_path)
    (tmp_path / "notes.txt").write_text("hi")
    with pytest.raises(SceneError, match="accepted are"):
        load_scene(tmp_path / "notes.txt")
    (tmp_path / "scene.json").write_text(json.dumps({"format": "visfly-scene", "version": 99}))
    with pytest.raises(SceneError, match="version 99"):
        load_scene(tmp_path)
    document = {"format": "visfly-scene", "version": 1, "name": "x", "bounds": [[0, 0, 0], [1, 1, 1]],
                "objects": [{"name": "evil", "id": 1, "mesh": "../outside.ply"}]}
    (tmp_path / "scene.json").write_text(json.dumps(document))
    with pytest.raises(SceneError, match="outside the scene roots"):
        load_scene(tmp_path)
