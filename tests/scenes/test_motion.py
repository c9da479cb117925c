"""Moving-obstacle paths against analytic results; their dicts, errors, and scenes that carry them."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from visfly_dist.errors import ConfigError, SceneError
from visfly_dist.scenes import generate_scene, load_scene, save_scene
from visfly_dist.scenes.motion import Circle, Polygon, Spline, motion_from_dict
from visfly_dist.scenes.scene import MOVING_KEY, Scene, SceneObject

SPLINE_POINTS = [[0.0, 0.0, 1.0], [4.0, -1.0, 1.5], [5.0, 3.0, 2.0], [1.0, 4.0, 1.0], [-1.0, 2.0, 1.2]]


def _finite_difference(motion, t, h=1e-5):
    return (motion.position(t + h) - motion.position(t - h)) / (2 * h)


def test_circle_speed_centripetal_acceleration_and_period():
    c = Circle([1.0, 2.0, 3.0], radius=2.0, speed=1.5, axis=[0.0, 0.0, 2.0], phase=0.3)
    t = np.linspace(-3.0, 20.0, 301)
    st = c.state(t)
    assert st.position.shape == st.velocity.shape == st.acceleration.shape == (301, 3)
    np.testing.assert_allclose(np.linalg.norm(st.position - c.centre, axis=1), 2.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(st.velocity, axis=1), 1.5, atol=1e-12)
    np.testing.assert_allclose(np.einsum("ij,ij->i", st.velocity, st.position - c.centre), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(st.acceleration, axis=1), 1.5 ** 2 / 2.0, atol=1e-12)
    np.testing.assert_allclose(st.acceleration, -(1.5 ** 2 / 2.0 ** 2) * (st.position - c.centre), atol=1e-12)
    np.testing.assert_allclose(st.position[:, 2], 3.0, atol=1e-12)   # in the plane normal to the axis
    assert c.period == pytest.approx(2 * np.pi * 2.0 / 1.5)
    np.testing.assert_allclose(c.position(t + c.period), st.position, atol=1e-9)
    np.testing.assert_allclose(c.position(0.0), [1.0 + 2 * np.cos(0.3), 2.0 + 2 * np.sin(0.3), 3.0], atol=1e-12)
    np.testing.assert_allclose(_finite_difference(c, t), st.velocity, atol=1e-6)
    # counter-clockwise about the axis
    assert np.all(np.cross(st.position - c.centre, st.velocity)[:, 2] > 0)


def test_circle_about_a_tilted_axis_stays_in_its_plane():
    axis = np.array([1.0, -2.0, 0.5])
    c = Circle([0.0, 0.0, 0.0], radius=1.0, speed=2.0, axis=axis)
    p = c.position(np.linspace(0, c.period, 50))
    np.testing.assert_allclose(p @ axis, 0.0, atol=1e-12)


def test_polygon_constant_speed_and_perimeter_time():
    square = [[0.0, 0.0, 1.0], [2.0, 0.0, 1.0], [2.0, 2.0, 1.0], [0.0, 2.0, 1.0]]
    p = Polygon(square, speed=0.5)
    assert p.length == pytest.approx(8.0) and p.period == pytest.approx(16.0)
    t = np.linspace(0.0, 40.0, 997)
    st = p.state(t)
    np.testing.assert_allclose(np.linalg.norm(st.velocity, axis=1), 0.5, atol=1e-12)
    np.testing.assert_array_equal(st.acceleration, 0.0)
    np.testing.assert_allclose(p.position([0.0, 4.0, 8.0, 12.0, 16.0]), np.array(square + [square[0]]), atol=1e-12)
    np.testing.assert_allclose(p.position(5.0), [2.0, 0.5, 1.0], atol=1e-12)   # 2.5 m along: on the second edge
    away = np.abs(np.mod(t, 4.0) - 2.0) < 1.9   # away from corners
    np.testing.assert_allclose(_finite_difference(p, t[away]), st.velocity[away], atol=1e-8)


def test_spline_passes_through_its_points_at_unit_speed_and_is_c2_at_the_seam():
    s = Spline(SPLINE_POINTS, speed=2.0)
    t = np.linspace(0.0, s.period, 2001)
    st = s.state(t)
    np.testing.assert_allclose(np.linalg.norm(st.velocity, axis=1), 2.0, atol=1e-9)
    np.testing.assert_allclose(_finite_difference(s, t), st.velocity, atol=1e-5)
    acc = (s.state(t + 1e-5).velocity - s.state(t - 1e-5).velocity) / 2e-5
    np.testing.assert_allclose(acc, st.acceleration, atol=1e-4)
    np.testing.assert_allclose(np.einsum("ij,ij->i", st.acceleration, st.velocity), 0.0, atol=1e-9)
    # passes through every point, in order, starting at the first at t = 0
    dense = s.position(np.linspace(0.0, s.period, 20001))
    for k, point in enumerate(SPLINE_POINTS):
        assert np.linalg.norm(dense - point, axis=1).min() < 2e-3, k
    np.testing.assert_allclose(s.position(0.0), SPLINE_POINTS[0], atol=1e-12)
    # periodic, and C2 across the seam
    e = 1e-7
    before, after = s.state(s.period - e), s.state(s.period + e)
    np.testing.assert_allclose(before.position, after.position, atol=1e-6)
    np.testing.assert_allclose(before.velocity, after.velocity, atol=1e-5)
    np.testing.assert_allclose(before.acceleration, after.acceleration, atol=1e-4)
    np.testing.assert_allclose(s.position(t + 3 * s.period), st.position, atol=1e-8)


def test_state_keeps_the_shape_of_t():
    c = Circle([0, 0, 0], 1.0, 1.0)
    assert c.state(0.5).position.shape == (3,)
    assert c.state(np.zeros((2, 5))).velocity.shape == (2, 5, 3)


@pytest.mark.parametrize("motion", [Circle([1, 2, 3], 2.0, 1.0, axis=[0, 1, 1], phase=1.0),
                                    Polygon([[0, 0, 1], [1, 0, 1], [1, 1, 2]], 0.7), Spline(SPLINE_POINTS, 1.3)])
def test_dict_round_trip_through_json_gives_the_same_states(motion):
    back = motion_from_dict(json.loads(json.dumps(motion.to_dict())))
    t = np.linspace(0, 30, 77)
    np.testing.assert_array_equal(back.position(t), motion.position(t))
    np.testing.assert_array_equal(back.state(t).acceleration, motion.state(t).acceleration)


@pytest.mark.parametrize("data, match", [
    ({"type": "helix", "speed": 1}, r"motion.type='helix' must be one of \['circle', 'polygon', 'spline'\]"),
    ([1, 2], "motion must be a dict"),
    ({"type": "circle", "centre": [0, 0, 0], "speed": 1}, r"missing field\(s\) \['radius'\]"),
    ({"type": "circle", "centre": [0, 0, 0], "radius": 1, "speed": 1, "colour": 3}, r"unknown field\(s\) \['colour'\]"),
    ({"type": "circle", "centre": [0, 0], "radius": 1, "speed": 1}, r"circle.centre=\[0, 0\] must be 3 finite"),
    ({"type": "circle", "centre": [0, 0, 0], "radius": -1, "speed": 1}, r"circle.radius=-1 must be finite"),
    ({"type": "circle", "centre": [0, 0, 0], "radius": 1, "speed": float("nan")}, r"circle.speed=nan"),
    ({"type": "circle", "centre": [0, 0, 0], "radius": 1, "speed": 1, "axis": [0, 0, 0]}, r"circle.axis=.*non-zero"),
    ({"type": "circle", "centre": [0, 0, 0], "radius": 1, "speed": True}, r"circle.speed=True must be a number"),
    ({"type": "polygon", "vertices": [[0, 0, 0]], "speed": 1}, r"polygon.vertices must be a list of 2 to"),
    ({"type": "polygon", "vertices": [[0, 0, 0], [1, 0, 0], [1, 0, 0]], "speed": 1}, r"polygon.vertices: point 1 .* coincide"),
    ({"type": "polygon", "vertices": [[0, 0, 0], [1, 0, 0]], "speed": 0}, r"polygon.speed=0 must be finite"),
    ({"type": "spline", "points": [[0, 0, 0], [1, 0, 0]], "speed": 1}, r"spline.points must be a list of 3 to"),
    ({"type": "spline", "points": [[0, 0, 0], [1, 0, 0], [1, "x", 0]], "speed": 1}, r"spline.points must be a list"),
])
def test_bad_motion_specs_name_the_field(data, match):
    with pytest.raises(ConfigError, match=match):
        motion_from_dict(data)


def _moving_scene() -> Scene:
    floor = trimesh.creation.box(extents=(10, 10, 0.1))
    cube = trimesh.creation.box(extents=(0.5, 0.5, 0.5))
    cube.visual.face_colors = [200, 30, 30, 255]
    motion = Circle([2.0, 0.0, 1.0], 1.5, 1.0)
    return Scene("m", [SceneObject("floor", 1, floor), SceneObject("cube", 2, cube, motion)],
                 np.array([[-5, -5, 0], [5, 5, 3]]))


def test_scene_lists_moving_objects_in_metadata_and_places_them():
    scene = _moving_scene()
    (entry,) = scene.metadata[MOVING_KEY]
    assert entry["object_id"] == 2 and entry["name"] == "cube"
    assert entry["radius"] == pytest.approx(np.sqrt(3) * 0.25)
    assert motion_from_dict(entry["motion"]).position(1.0).tolist() == scene.objects[1].motion.position(1.0).tolist()
    placed = scene.at_time(2.0)
    assert not placed.moving_objects and MOVING_KEY not in placed.metadata
    np.testing.assert_allclose(placed.objects[1].mesh.vertices.mean(axis=0), scene.objects[1].motion.position(2.0), atol=1e-12)
    assert placed.objects[0] is scene.objects[0]


def test_scene_directory_round_trip_keeps_motions(tmp_path):
    scene = _moving_scene()
    back = load_scene(save_scene(scene, tmp_path / "s"))
    assert [o.motion is None for o in back.objects] == [True, False]
    assert back.objects[1].motion.to_dict() == scene.objects[1].motion.to_dict()
    assert back.metadata[MOVING_KEY] == json.loads(json.dumps(scene.metadata[MOVING_KEY]))


def test_scene_file_with_a_bad_motion_names_the_object_and_field(tmp_path):
    path = save_scene(_moving_scene(), tmp_path / "s") / "scene.json"
    document = json.loads(path.read_text())
    document["objects"][1]["motion"]["radius"] = "big"
    path.write_text(json.dumps(document))
    with pytest.raises(SceneError, match=r"objects\[1\].motion: circle.radius='big' must be a number"):
        load_scene(path)


def test_garage_moving_stones_are_deterministic_and_leave_the_static_scene_as_it_was():
    plain = generate_scene("garage-stones", seed=4, density=0.05)
    moving = generate_scene("garage-stones", seed=4, density=0.05, moving=6)
    assert moving.name == "gen:garage-stones?seed=4&density=0.05&moving=6"
    assert len(moving.moving_objects) == 6 and len(moving.static_objects) == len(plain.objects)
    for a, b in zip(plain.objects, moving.static_objects):
        assert a.name == b.name and np.array_equal(a.mesh.vertices, b.mesh.vertices)
    again = generate_scene("garage-stones", seed=4, density=0.05, moving=6)
    assert again.metadata[MOVING_KEY] == moving.metadata[MOVING_KEY]
    assert {m["motion"]["type"] for m in moving.metadata[MOVING_KEY]} <= {"circle", "polygon", "spline"}
    start_low, start_high = np.asarray(moving.metadata["start_region"])
    for obj in moving.moving_objects:   # the swept path keeps clear of the start region
        path = obj.motion.path_points(0.05)
        gap = np.linalg.norm(path - np.clip(path, start_low, start_high), axis=1)
        assert gap.min() >= obj.bounding_radius
    with pytest.raises(SceneError, match=r"moving=101 must be in \[0, 100\]"):
        generate_scene("garage-stones", moving=101)


@pytest.mark.parametrize("motion", [Circle([1, 2, 3], 2.0, 1.0, phase=1.0), Polygon([[0, 0, 1], [1, 0, 1], [1, 1, 2]], 0.7),
                                    Spline(SPLINE_POINTS, 1.3)])
def test_one_instant_agrees_with_the_vectorised_path(motion):
    times = np.linspace(-5.0, 40.0, 91)
    batch = motion.state(times)
    for k, t in enumerate(times):
        one = motion.state(float(t))
        np.testing.assert_allclose(one.position, batch.position[k], rtol=0, atol=1e-12)
        np.testing.assert_allclose(one.velocity, batch.velocity[k], rtol=0, atol=1e-12)
        np.testing.assert_allclose(one.acceleration, batch.acceleration[k], rtol=0, atol=1e-10)
    assert motion.state(2.0) is motion.state(2.0) and not motion.state(2.0).position.flags.writeable
