"""Obstacle queries against analytic answers: distance, nearest point, collision, inside, cap."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from visfly_dist.errors import ConfigError
from visfly_dist.scene_worker.queries import ObstacleQueries
from visfly_dist.scenes.scene import Scene, SceneObject

RADIUS = 0.1


@pytest.fixture(scope="module")
def queries() -> ObstacleQueries:
    """A closed 2 m cube centred on the origin and an open floor plane at z = -3."""
    cube = trimesh.creation.box((2.0, 2.0, 2.0))
    floor = trimesh.Trimesh([[-10, -10, -3], [10, -10, -3], [10, 10, -3], [-10, 10, -3]], [[0, 1, 2], [0, 2, 3]])
    objects = [SceneObject("cube", 1, cube), SceneObject("floor", 2, floor)]
    scene = Scene("q", objects, np.array([[-9, -9, -2.9], [9, 9, 9]]))
    return ObstacleQueries(scene, drone_radius=RADIUS)


def one(queries: ObstacleQueries, point, search_radius=5.0):
    r = queries.query(np.array([point], dtype=float), search_radius)
    assert r.nearest.dtype == np.float32 and r.distance.dtype == np.float32
    return bool(r.collision[0]), bool(r.inside[0]), r.nearest[0].astype(float), float(r.distance[0])


def test_near_a_face_gives_the_centre_distance_and_the_foot_point(queries):
    collision, inside, nearest, distance = one(queries, [1.7, 0.2, -0.3])
    assert (collision, inside) == (False, False)
    assert distance == pytest.approx(0.7, abs=1e-6)           # from the drone CENTRE, not its sphere
    np.testing.assert_allclose(nearest, [1.0, 0.2, -0.3], atol=1e-6)


def test_near_an_edge_points_at_the_edge(queries):
    _, _, nearest, distance = one(queries, [1.5, 1.5, 0.25])
    assert distance == pytest.approx(np.sqrt(0.5), abs=1e-6)
    np.testing.assert_allclose(nearest, [1.0, 1.0, 0.25], atol=1e-6)


def test_near_the_open_plane(queries):
    collision, inside, nearest, distance = one(queries, [4.0, -5.0, -2.5])
    assert (collision, inside) == (False, False)
    assert distance == pytest.approx(0.5, abs=1e-6)
    np.testing.assert_allclose(nearest, [4.0, -5.0, -3.0], atol=1e-6)


def test_overlapping_sphere_collides_with_the_true_nearest_point(queries):
    collision, inside, nearest, distance = one(queries, [1.06, 0.3, 0.4])
    assert (collision, inside) == (True, False)
    assert distance == pytest.approx(0.06, abs=1e-6)
    np.testing.assert_allclose(nearest, [1.0, 0.3, 0.4], atol=1e-6)


def test_touching_counts_as_collision_and_just_clear_does_not(queries):
    r = queries.query(np.array([[0.0, 0.0, 1.0 + RADIUS - 1e-6], [0.0, 0.0, 1.0 + RADIUS + 1e-4]]), 5.0)
    np.testing.assert_array_equal(r.collision, [True, False])


def test_wholly_inside_a_closed_box_is_inside_and_colliding(queries):
    collision, inside, nearest, distance = one(queries, [0.2, -0.1, 0.0])
    assert (collision, inside) == (True, True)
    assert distance == 0.0
    np.testing.assert_allclose(nearest, [1.0, -0.1, 0.0], atol=1e-6)   # the way out: the nearest face
    assert queries.distance(np.array([[0.2, -0.1, 0.0]]))[0] == pytest.approx(-0.8, abs=1e-6)


def test_far_away_distance_is_capped_along_the_true_direction(queries):
    collision, inside, nearest, distance = one(queries, [3.5, 0.0, 0.5], search_radius=2.0)
    assert (collision, inside) == (False, False)
    assert distance == pytest.approx(2.0)
    np.testing.assert_allclose(nearest, [1.5, 0.0, 0.5], atol=1e-5)
    assert queries.distance(np.array([[3.5, 0.0, 0.5]]))[0] == pytest.approx(2.5, abs=1e-6)


def test_batch_matches_single_queries(queries):
    points = np.random.default_rng(3).uniform(-3, 3, size=(40, 3))
    batch = queries.query(points, 1.5)
    for i, p in enumerate(points):
        collision, inside, nearest, distance = one(queries, p, 1.5)
        assert (batch.collision[i], batch.inside[i]) == (collision, inside)
        assert batch.distance[i] == pytest.approx(distance, abs=1e-6)
        inside_cube = np.all(np.abs(p) < 1.0)
        assert batch.inside[i] == inside_cube
        assert batch.distance[i] <= 1.5


def test_empty_scene_answers_nothing_near():
    q = ObstacleQueries(Scene("empty", [], np.array([[0, 0, 0], [1, 1, 1]])), drone_radius=RADIUS)
    r = q.query(np.array([[0.5, 0.5, 0.5]]), 3.0)
    assert not r.collision[0] and not r.inside[0] and r.distance[0] == 3.0
    np.testing.assert_allclose(r.nearest[0], [0.5, 0.5, -2.5])
    assert q.distance(np.array([[0.5, 0.5, 0.5]]))[0] == np.inf


def test_bad_input_is_refused(queries):
    with pytest.raises(ConfigError, match=r"positions shape \(3,\) must be \(n, 3\)"):
        queries.query(np.zeros(3), 1.0)
    with pytest.raises(ConfigError, match="search_radius=-1.0"):
        queries.query(np.zeros((1, 3)), -1.0)


def _split_vertex_glb(tmp_path, name: str, meshes) -> "Scene":
    """Meshes written to one glb with every face on its own vertices (as glTF exporters split them)."""
    from visfly_dist.scenes import load_scene

    tscene = trimesh.Scene()
    for i, mesh in enumerate(meshes):
        split = mesh.copy()
        split.unmerge_vertices()
        tscene.add_geometry(split, node_name=f"{name}{i}")
    tscene.export(tmp_path / f"{name}.glb")
    scene = load_scene(tmp_path / f"{name}.glb", up_axis="z")
    assert not any(o.mesh.is_watertight for o in scene.objects)   # what used to hide the inside
    return scene


def test_split_vertex_glb_box_and_sphere_are_solid(tmp_path):
    box = trimesh.creation.box((2.0, 2.0, 2.0))
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    sphere.apply_translation([5.0, 0.0, 0.0])
    scene = _split_vertex_glb(tmp_path, "solids", [box, sphere])
    q = ObstacleQueries(scene, drone_radius=RADIUS)
    r = q.query(np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [5.3, 0.2, -0.1], [2.5, 0.0, 0.0]]), 5.0)
    np.testing.assert_array_equal(r.inside, [True, True, True, False])
    np.testing.assert_array_equal(r.collision, [True, True, True, False])
    np.testing.assert_array_equal(r.distance[:3], 0.0)


def test_open_plane_and_open_box_have_no_inside(tmp_path):
    plane = trimesh.Trimesh([[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]], [[0, 1, 2], [0, 2, 3]])
    lidless = trimesh.creation.box((2.0, 2.0, 2.0))
    lidless.update_faces(lidless.face_normals[:, 2] < 0.5)      # the top face removed
    lidless.apply_translation([0.0, 0.0, 3.0])
    scene = _split_vertex_glb(tmp_path, "open", [plane, lidless])
    q = ObstacleQueries(scene, drone_radius=RADIUS)
    points = np.random.default_rng(0).uniform([-4, -4, -2], [4, 4, 5], size=(300, 3))
    points[:50] = np.random.default_rng(1).uniform([-0.9, -0.9, 2.1], [0.9, 0.9, 3.9], size=(50, 3))
    assert not q.query(points, 5.0).inside.any()
    assert np.all(q.distance(points) >= 0)


def test_overlapping_closed_parts_of_one_object_are_each_solid():
    a = trimesh.creation.box((2.0, 2.0, 2.0))
    b = trimesh.creation.box((2.0, 2.0, 2.0))
    b.apply_translation([1.0, 0.0, 0.0])
    both = trimesh.util.concatenate([a, b])      # one object, two closed components overlapping
    q = ObstacleQueries(Scene("o", [SceneObject("two", 1, both)], np.array([[-5] * 3, [5] * 3])), RADIUS)
    np.testing.assert_array_equal(q.query(np.array([[0.5, 0.0, 0.0], [-0.5, 0, 0], [1.5, 0, 0], [3, 0, 0]]), 5.0).inside,
                                  [True, True, True, False])


def test_no_spawn_inside_a_closed_obstacle(tmp_path):
    from visfly_dist.scenes import sample_free_positions

    scene = _split_vertex_glb(tmp_path, "block", [trimesh.creation.box((2.0, 2.0, 2.0))])
    q = ObstacleQueries(scene, drone_radius=RADIUS)
    spawns = sample_free_positions(200, 0.5, "uniform", [-1.5] * 3, [1.5] * 3, np.random.default_rng(0), q.distance)
    outside_by = np.linalg.norm(spawns - np.clip(spawns, -1.0, 1.0), axis=1)
    assert np.all(outside_by >= 0.5 - 1e-6)


def test_a_closed_room_facing_inwards_is_free_space_inside():
    room = trimesh.creation.box((10.0, 10.0, 4.0))
    room.invert()                                   # normals inwards: a room seen from within
    q = ObstacleQueries(Scene("room", [SceneObject("room", 1, room)], np.array([[-5, -5, -2], [5, 5, 2]])), RADIUS)
    r = q.query(np.array([[0.0, 0.0, 0.0], [4.0, 4.0, 1.5]]), 5.0)
    np.testing.assert_array_equal(r.inside, [False, False])
    np.testing.assert_allclose(r.distance, [2.0, 0.5], atol=1e-6)


@pytest.mark.parametrize("shift", [0.0, 5000.0, -120_000.0])
def test_inside_holds_kilometres_from_the_origin(shift):
    """A georeferenced scene (kilometres out) and a scene spanning kilometres (a mesh in millimetres):
    float32 parity rays still step past each surface, so a solid's inside is inside."""
    near, far = trimesh.creation.box((1.0, 1.0, 2.0)), trimesh.creation.box((1.0, 1.0, 2.0))
    near.apply_translation((shift + 5.0, shift, 1.0))
    far.apply_translation((shift + 8000.0, shift + 5000.0, 1.0))  # 9 km from the other box
    objects = [SceneObject("near", 1, near), SceneObject("far", 2, far)]
    q = ObstacleQueries(Scene("geo", objects, np.array([[0, -1, 0], [8001, 5001, 3]]) + shift), drone_radius=RADIUS)
    points = np.array([[5.0, 0.0, 1.0], [8000.0, 5000.0, 1.0], [8000.2, 5000.3, 0.4], [5.0, 0.0, 2.6]]) + [shift, shift, 0]
    r = q.query(points, 5.0)
    np.testing.assert_array_equal(r.inside, [True, True, True, False])
    np.testing.assert_allclose(q.distance(points), [-0.5, -0.5, -0.2, 0.6], atol=1e-3)


@pytest.mark.parametrize("backend", ["native", "fcl"])
def test_several_scenes_in_one_call_answer_as_each_scene_alone(backend):
    """query_scenes (a worker's scenes together, one native call) equals each scene's own query,
    row for row, with scenes of other sizes, drone radii, an empty scene and a scene with no rows."""
    from visfly_dist.scene_worker import render_native
    from visfly_dist.scene_worker.queries import query_scenes

    if backend == "native" and not render_native.available():
        pytest.skip("native library not built")
    rng = np.random.default_rng(11)
    scenes = []
    for k, size in enumerate((2.0, 1.0, 3.0)):
        box = trimesh.creation.box((size, size, size))
        box.apply_translation((k, 0, 0))
        scenes.append(Scene(f"s{k}", [SceneObject("box", 1, box)], np.array([[-9, -9, -9], [9, 9, 9]])))
    scenes.append(Scene("empty", [], np.array([[0, 0, 0], [1, 1, 1]])))
    queries = [ObstacleQueries(s, drone_radius=r, backend=backend) for s, r in zip(scenes, (0.1, 0.3, 0.2, 0.1))]
    items = [(q, rng.uniform(-3, 3, size=(n, 3)), 0.0) for q, n in zip(queries, (7, 0, 12, 3))]
    together = query_scenes(items, 2.0)
    alone = [q.query(p, 2.0) for q, p, _ in items]
    for field in ("collision", "inside", "nearest", "distance"):
        expected = np.concatenate([getattr(a, field) for a in alone])
        np.testing.assert_array_equal(getattr(together, field), expected, err_msg=field)
    assert together.inside.any() and together.collision.any() and not together.collision.all()
