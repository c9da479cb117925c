"""Scene generators: determinism, kept-clear regions, density, params and errors."""

from __future__ import annotations

import numpy as np
import pytest

from visfly_dist.errors import SceneError
from visfly_dist.scenes import GENERATORS, generate_scene
from visfly_dist.scene_worker.scenes_cli import KINDS
from visfly_dist.scenes.primitives import sphere_hits_box

ALL_KINDS = sorted(GENERATORS)


def _same(a, b) -> bool:
    return len(a.objects) == len(b.objects) and all(
        x.name == y.name and x.object_id == y.object_id
        and np.array_equal(x.mesh.vertices, y.mesh.vertices) and np.array_equal(x.mesh.faces, y.mesh.faces)
        and np.array_equal(x.mesh.visual.face_colors, y.mesh.visual.face_colors)
        for x, y in zip(a.objects, b.objects)
    )


def test_registry_lists_the_contract_kinds_and_documents_params():
    assert ALL_KINDS == sorted(KINDS) == ["empty", "gap-walls", "garage-stones", "landing-pad", "pillars"]
    for kind, generate in GENERATORS.items():
        for param in generate.params:
            assert param in generate.__doc__, (kind, param)


@pytest.mark.parametrize("kind", ALL_KINDS)
def test_same_seed_same_meshes(kind):
    a, b = generate_scene(kind, seed=5), generate_scene(kind, seed=5)
    assert _same(a, b)
    assert a.name == b.name == f"gen:{kind}?seed=5"
    assert a.metadata == b.metadata and a.metadata["kind"] == kind and a.metadata["seed"] == 5
    ids = [o.object_id for o in a.objects]
    assert ids == list(range(1, len(ids) + 1))


@pytest.mark.parametrize("kind", ["garage-stones", "pillars"])
def test_seeds_differ(kind):
    assert not _same(generate_scene(kind, seed=1), generate_scene(kind, seed=2))


def test_garage_stones_layout_and_regions_clear():
    scene = generate_scene("garage-stones", seed=0)
    np.testing.assert_array_equal(scene.bounds, [[0, -7, 0], [18, 7, 5]])
    meta = scene.metadata
    assert meta["start_region"] == [[0.0, -2.0, 0.5], [2.0, 2.0, 2.5]]
    assert meta["goal"] == [9.0, 0.0, 1.0]
    stones = [o for o in scene.objects if o.name.startswith("stone_")]
    assert len(stones) == meta["num_stones"] == round(18 * 14 * 5 * 0.15)
    assert 10_000 < scene.num_triangles < 60_000
    for key in ("start_region", "goal_region"):
        low, high = np.asarray(meta[key]) + [[-0.2] * 3, [0.2] * 3]  # default margin
        for s in stones:
            center = s.mesh.bounds.mean(axis=0)
            radius = np.linalg.norm(s.mesh.vertices - center, axis=1).max()
            assert not sphere_hits_box(center[None], radius, low, high)[0], (key, s.name)


def test_region_margins_are_params():
    scene = generate_scene("garage-stones", seed=0, start_center=(4, 0, 2.5), start_half=(3, 3, 2.5), margin=0.0)
    low, high = np.asarray(scene.metadata["start_region"])
    np.testing.assert_allclose([low, high], [[1, -3, 0], [7, 3, 5]])
    for s in scene.objects[6:]:
        v = s.mesh.vertices
        assert not np.any(np.all((v > low) & (v < high), axis=1)), s.name
    assert scene.metadata["params"]["start_half"] == [3.0, 3.0, 2.5]


def test_density_scales_stone_count():
    counts = [generate_scene("garage-stones", seed=0, density=d).metadata["num_stones"] for d in (0.0, 0.05, 0.1)]
    assert counts == [0, 63, 126]
    assert len(generate_scene("garage-stones", seed=0, density=0.0).objects) == 6
    assert generate_scene("pillars", seed=0, density=0.05).metadata["num_pillars"] == round(18 * 14 * 0.05)


def test_gap_walls_leave_the_gap_open():
    scene = generate_scene("gap-walls", seed=0, gap_width=1.2, wall_x=9.0)
    left, right = scene.objects[-2].mesh.bounds, scene.objects[-1].mesh.bounds
    assert left[1, 1] == pytest.approx(-0.6) and right[0, 1] == pytest.approx(0.6)
    for b in (left, right):
        assert b[0, 0] == pytest.approx(8.9) and b[1, 0] == pytest.approx(9.1)
        assert b[0, 2] == pytest.approx(0.0) and b[1, 2] == pytest.approx(5.0)
    assert scene.metadata["gap_center"] == [9.0, 0.0, 2.5]
    with pytest.raises(SceneError, match="gap_width=20"):
        generate_scene("gap-walls", gap_width=20)


def test_gap_walls_spread_moves_the_gap_with_the_seed():
    centres = [generate_scene("gap-walls", seed=seed, gap_y_spread=1.5).metadata["gap_center"][1] for seed in range(12)]
    assert all(-1.5 <= y <= 1.5 for y in centres) and len(set(centres)) == 12 and max(centres) - min(centres) > 1.0
    scene = generate_scene("gap-walls", seed=3, gap_y_spread=1.5, gap_width=0.8)
    gap_y = scene.metadata["gap_center"][1]
    left, right = scene.objects[-2].mesh.bounds, scene.objects[-1].mesh.bounds
    assert left[1, 1] == pytest.approx(gap_y - 0.4) and right[0, 1] == pytest.approx(gap_y + 0.4)
    assert generate_scene("gap-walls", seed=3, gap_y_spread=1.5).metadata == scene.metadata  # same seed, same wall
    with pytest.raises(SceneError, match="gap_y_spread=6.8"):
        generate_scene("gap-walls", gap_y_spread=6.8)


def test_landing_pad_is_black_and_its_own_object():
    scene = generate_scene("landing-pad")
    pad = scene.object_by_id(2)
    assert pad.name == "pad"
    np.testing.assert_allclose(pad.mesh.bounds, [[1.75, -0.25, 0.0], [2.25, 0.25, 0.01]], atol=1e-6)
    assert np.all(pad.mesh.visual.face_colors[:, :3] == 0)
    floor_rgb = scene.object_by_id(1).mesh.visual.face_colors[0, :3].astype(int)
    assert 100 < floor_rgb.mean() < 200
    assert scene.metadata["pad_center"] == [2.0, 0.0, 0.0]
    np.testing.assert_array_equal(scene.bounds, [[-3, -5, 0], [7, 5, 5]])


def test_pillars_clear_regions_in_plan_view():
    scene = generate_scene("pillars", seed=3, density=0.3)
    for key in ("start_region", "goal_region"):
        low, high = np.asarray(scene.metadata[key])[:, :2] + [[-0.2, -0.2], [0.2, 0.2]]
        for p in scene.objects[6:]:
            center = p.mesh.bounds.mean(axis=0)[:2]
            radius = (p.mesh.bounds[1, 0] - p.mesh.bounds[0, 0]) / 2
            assert np.linalg.norm(center - np.clip(center, low, high)) >= radius - 1e-6, (key, p.name)


def test_empty_is_a_floor():
    scene = generate_scene("empty")
    assert [o.name for o in scene.objects] == ["floor"]
    np.testing.assert_array_equal(scene.bounds, [[-10, -10, 0], [10, 10, 10]])
    assert scene.object_by_id(1).mesh.bounds[1, 2] == 0.0


def test_errors_name_valid_choices():
    with pytest.raises(SceneError, match=r"unknown scene kind 'forest'.*garage-stones"):
        generate_scene("forest")
    with pytest.raises(SceneError, match=r"unknown param\(s\) \['densty'\].*valid params: .*'density'"):
        generate_scene("garage-stones", densty=0.1)
    with pytest.raises(SceneError, match="valid params: \\[\\]"):
        generate_scene("empty", density=1)
    with pytest.raises(SceneError, match="seed=-1"):
        generate_scene("empty", seed=-1)
    with pytest.raises(SceneError, match="start_center"):
        generate_scene("garage-stones", start_center=(1, 2))
    with pytest.raises(SceneError, match="keep-clear"):
        generate_scene("garage-stones", start_center=(9, 0, 2.5), start_half=(9, 7, 2.5))
