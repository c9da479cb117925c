"""Surface shading at hits: bilinear texture sampling, plain colours, and raycast RGB of a textured glb vs egl."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from PIL import Image
from scipy.ndimage import binary_erosion

from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.scene_worker.render_base import available_backends, face_rgb, make_renderer
from visfly_dist.scene_worker.shading import SurfaceShader, sample_bilinear
from visfly_dist.scenes import load_scene
from visfly_dist.scenes.scene import Scene, SceneObject

TEXELS = np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 0]],
                   [[0, 255, 255], [255, 0, 255], [40, 40, 40], [250, 250, 250]],
                   [[128, 0, 0], [0, 128, 0], [0, 0, 128], [128, 128, 0]],
                   [[200, 100, 50], [50, 100, 200], [100, 200, 50], [10, 20, 30]]], np.uint8)


def textured_quad(factor=(255, 255, 255, 255)) -> trimesh.Trimesh:
    """A 4 x 4 m wall in the plane x = 3 facing -x, UV (0,0) at its bottom-left seen from the origin."""
    vertices = np.array([[3.0, 2.0, -2.0], [3.0, -2.0, -2.0], [3.0, -2.0, 2.0], [3.0, 2.0, 2.0]])
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    material = trimesh.visual.material.PBRMaterial(baseColorTexture=Image.fromarray(TEXELS), baseColorFactor=factor,
                                                   metallicFactor=0.0, roughnessFactor=1.0)
    return trimesh.Trimesh(vertices, [[0, 1, 2], [0, 2, 3]], visual=trimesh.visual.TextureVisuals(uv=uv, material=material),
                           process=False)


def test_bilinear_sampling_hits_texel_centres_and_blends_between_them():
    image = TEXELS.astype(np.float32)
    centre_of = lambda row, col: [(col + 0.5) / 4, 1 - (row + 0.5) / 4]  # noqa: E731  v up: row 0 is the top
    np.testing.assert_allclose(sample_bilinear(image, np.array([centre_of(0, 0), centre_of(3, 2)])), image[[0, 3], [0, 2]])
    np.testing.assert_allclose(sample_bilinear(image, np.array([[0.25, 1 - 0.125]])), [(image[0, 0] + image[0, 1]) / 2])
    # repeat wrap: half way between the last and the first column
    np.testing.assert_allclose(sample_bilinear(image, np.array([[1.0, 1 - 0.125]])), [(image[0, 3] + image[0, 0]) / 2])


def test_colours_of_textured_vertex_and_face_coloured_meshes():
    quad = textured_quad(factor=(255, 128, 255, 255))
    vertex = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]],
                             vertex_colors=[[255, 0, 0, 255], [0, 255, 0, 255], [0, 0, 255, 255]], process=False)
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], face_colors=[[10, 20, 30, 255]], process=False)
    shader = SurfaceShader([quad, vertex, flat])
    # Face 1 of the quad (corners 0, 2, 3): u = weight of corner 2 (uv 1,1), v = of corner 3 (uv 0,1).
    u, v = np.array([0.5 / 4, 0.0, 0.2, 0.3]), np.array([(3.5 - 0.5) / 4, 0.0, 0.5, 0.3])
    colors = shader.colors(np.array([1, 2, 2, 3]), u, v)
    np.testing.assert_allclose(colors[0], TEXELS[0, 0] * [1.0, 128 / 255, 1.0], atol=1e-3)   # texel (0, 0) x factor
    np.testing.assert_allclose(colors[1], [255, 0, 0])
    np.testing.assert_allclose(colors[2], [0.3 * 255, 0.2 * 255, 0.5 * 255], atol=1e-3)
    np.testing.assert_allclose(colors[3], [10, 20, 30])
    single = SurfaceShader([quad, vertex, flat], single_geometry=False)
    np.testing.assert_array_equal(single.faces(np.array([0, 1, 2, 0]), np.array([1, 0, 0, -1])), [1, 2, 3, -1])


def test_face_rgb_of_a_textured_mesh_samples_the_face_centroid():
    colors = face_rgb(textured_quad())
    assert colors.shape == (2, 3) and colors.dtype == np.uint8
    uv_centroid = np.array([[2 / 3, 1 / 3], [1 / 3, 2 / 3]])
    np.testing.assert_allclose(colors, sample_bilinear(TEXELS.astype(np.float32), uv_centroid), atol=0.5)


@pytest.mark.skipif(not {"egl", "raycast"} <= set(available_backends()), reason="needs both backends")
def test_textured_glb_raycast_matches_egl(tmp_path):
    textured_quad().export(tmp_path / "wall.glb")
    scene = load_scene(tmp_path / "wall.glb", up_axis="z")
    assert scene.objects[0].mesh.visual.kind == "texture"
    camera = CameraSpec(name="rgb", kind="rgb", width=64, height=64)
    seg = CameraSpec(name="seg", kind="segmentation", width=64, height=64)
    pose = np.array([[0.0, 0.3, 0.2, 1.0, 0.0, 0.0, 0.0]])
    images = {}
    for backend in ("raycast", "egl"):
        with make_renderer(backend, scene, [camera, seg]) as renderer:
            images[backend] = renderer.render(pose)
    wall = images["raycast"]["seg"][0, 0] > 0
    away = binary_erosion(wall, iterations=2)    # away from the wall's edges (egl multisamples them)
    assert away.sum() > 1000
    rgb_raycast = images["raycast"]["rgb"][0].astype(float)
    rgb_egl = images["egl"]["rgb"][0].astype(float)
    diff = np.abs(rgb_raycast - rgb_egl)[:, away].mean()
    print(f"mean abs diff raycast vs egl away from edges: {diff:.2f} / 255")
    assert diff < 10
    # the texture is really there: the wall shows many colours, not one average
    assert len(np.unique(images["raycast"]["rgb"][0][:, away].T, axis=0)) > 8
