"""resolve_source: gen: specs, paths confined to the scene roots, the in-process cache."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import trimesh

from visfly_dist.errors import SceneError
from visfly_dist.scenes import generate_scene, resolve_source, save_scene
from visfly_dist.scenes.sources import parse_gen_spec


@pytest.fixture
def root(tmp_path):
    directory = tmp_path / "root"
    save_scene(generate_scene("landing-pad"), directory / "pad")
    trimesh.creation.box().export(directory / "box.stl")
    return directory


def test_gen_spec_parses_numbers_and_tuples():
    assert parse_gen_spec("gen:garage-stones?seed=3&density=0.2&start_half=1,2,0.5") == (
        "garage-stones", 3, {"density": 0.2, "start_half": (1.0, 2.0, 0.5)})
    assert parse_gen_spec("gen:empty") == ("empty", 0, {})
    scene = resolve_source("gen:garage-stones?seed=3&density=0.02", roots=[])
    assert scene.metadata["seed"] == 3 and scene.metadata["num_stones"] == round(1260 * 0.02)
    with pytest.raises(SceneError, match="seed=1.5"):
        parse_gen_spec("gen:empty?seed=1.5")
    with pytest.raises(SceneError, match="'abc' is not a number"):
        parse_gen_spec("gen:empty?x=abc")
    with pytest.raises(SceneError, match="unknown scene kind 'nope'"):
        resolve_source("gen:nope?seed=1", roots=[])


def test_generated_scenes_are_cached_by_spec():
    a = resolve_source("gen:pillars?seed=11&density=0.05", roots=[])
    assert resolve_source("gen:pillars?density=0.05&seed=11", roots=[]) is a
    assert resolve_source("gen:pillars?seed=12&density=0.05", roots=[]) is not a


def test_paths_inside_roots_load(root, tmp_path):
    other = tmp_path / "other"
    other.mkdir()
    assert resolve_source("pad", roots=[other, root]).metadata["kind"] == "landing-pad"
    assert resolve_source("pad/scene.json", roots=[root]).object_by_id(2).name == "pad"
    assert resolve_source(str(root / "box.stl"), roots=[root]).num_triangles == 12
    assert resolve_source("pad/../box.stl", roots=[root]).num_triangles == 12


def test_paths_outside_roots_are_refused(root, tmp_path):
    roots_pattern = "outside the scene roots"
    with pytest.raises(SceneError, match=rf"'\.\./\.\./etc/passwd'.*{roots_pattern}"):
        resolve_source("../../etc/passwd", roots=[root])
    with pytest.raises(SceneError, match=rf"'/etc/passwd'.*{roots_pattern}.*{root.name}"):
        resolve_source("/etc/passwd", roots=[root])
    save_scene(generate_scene("empty"), tmp_path / "secret")
    os.symlink(tmp_path / "secret", root / "link")
    with pytest.raises(SceneError, match=roots_pattern):
        resolve_source("link", roots=[root])
    with pytest.raises(SceneError, match="no scene roots are configured"):
        resolve_source("pad", roots=[])


def test_missing_and_referenced_files(root, tmp_path):
    with pytest.raises(SceneError, match=r"'missing.glb' not found under the scene roots"):
        resolve_source("missing.glb", roots=[root])
    (tmp_path / "data.bin").write_bytes(b"\0" * 16)
    gltf = {"asset": {"version": "2.0"}, "buffers": [{"uri": "../data.bin", "byteLength": 16}]}
    (root / "sneaky.gltf").write_text(json.dumps(gltf))
    with pytest.raises(SceneError, match=r"referenced by sneaky.gltf.*outside the scene roots"):
        resolve_source("sneaky.gltf", roots=[root])


def test_mesh_files_of_a_scene_dir_stay_inside(root, tmp_path):
    document = json.loads((root / "pad/scene.json").read_text())
    trimesh.creation.box().export(tmp_path / "evil.ply")
    document["objects"][0]["mesh"] = "../../evil.ply"
    (root / "pad/scene.json").write_text(json.dumps(document))
    with pytest.raises(SceneError, match="evil.ply"):
        resolve_source("pad", roots=[root])
    assert np.all(resolve_source("box.stl", roots=[root]).bounds[1] == 0.5)


@pytest.fixture
def tall_glb(root):
    """A 1 x 1 x 4 m box authored z-up (its long side along z), saved as glb (y-up by specification)."""
    trimesh.creation.box((1.0, 1.0, 4.0), transform=trimesh.transformations.translation_matrix([0, 0, 2])).export(
        root / "tall.glb")
    return "tall.glb"


def test_up_axis_travels_in_the_source_string(root, tall_glb):
    upright = resolve_source(f"{tall_glb}?up=z", roots=[root])
    np.testing.assert_allclose(upright.bounds, [[-0.5, -0.5, 0.0], [0.5, 0.5, 4.0]], atol=1e-9)
    assert upright.metadata["up_axis"] == "z"
    lying = resolve_source(tall_glb, roots=[root])               # glTF default y-up: on its side
    np.testing.assert_allclose(lying.bounds, [[-0.5, -4.0, -0.5], [0.5, 0.0, 0.5]], atol=1e-9)
    assert resolve_source(f"{tall_glb}?up=y", roots=[root]).metadata["up_axis"] == "y"


def test_worker_load_request_and_env_sources_carry_the_up_axis(root, tall_glb):
    from visfly_dist.aggregator.dataset import expand_sources
    from visfly_dist.protocol.cameras import CameraSpec
    from visfly_dist.protocol.messages import LoadScene
    from visfly_dist.scene_worker.state import assemble_scene, prepare_scene

    request = LoadScene("k", f"{tall_glb}?up=z", (CameraSpec(width=8, height=8),))
    loaded = assemble_scene(prepare_scene(request, [root], "raycast"), "raycast")
    try:
        assert loaded.scene.bounds[1, 2] == pytest.approx(4.0)
    finally:
        loaded.renderer.close()
    assert expand_sources(("*.glb?up=z", str(root / "tall.glb") + "?up=y"), (str(root),)) == ["tall.glb?up=z", "tall.glb?up=y"]


@pytest.mark.parametrize("source, message", [
    ("tall.glb?up=x", r"option 'up=x' is not valid; accepted: up=y\|z"),
    ("tall.glb?upp=z", r"option 'upp=z' is not valid"),
    ("tall.glb?up", r"option 'up' is not valid"),
    ("tall.glb?up=z&up=y", r"option 'up=y' is not valid.*at most once"),
    ("pad/scene.json?up=z", r"apply to mesh files .* only"),
])
def test_bad_source_options_are_refused(root, tall_glb, source, message):
    with pytest.raises(SceneError, match=message):
        resolve_source(source, roots=[root])


def test_a_mesh_kilometres_wide_loads_with_a_word_on_its_units(tmp_path, caplog):
    from visfly_dist.scenes.meshes import load_mesh_file

    box = trimesh.creation.box((14000.0, 10000.0, 4000.0))  # a 14 x 10 x 4 m garage exported in millimetres
    box.export(tmp_path / "garage_mm.stl")
    with caplog.at_level("WARNING", logger="visfly_dist.scenes.meshes"):
        scene = load_mesh_file(tmp_path / "garage_mm.stl")
    assert np.allclose(scene.bounds[1] - scene.bounds[0], [14000, 10000, 4000])  # loaded as it is
    assert any("spans 14000 m; scene units are metres" in r.getMessage() for r in caplog.records)
    caplog.clear()
    trimesh.creation.box((14.0, 10.0, 4.0)).export(tmp_path / "garage.stl")
    with caplog.at_level("WARNING", logger="visfly_dist.scenes.meshes"):
        load_mesh_file(tmp_path / "garage.stl")
    assert not caplog.records
