"""The ``egl`` backend as it was before the batch renderer (issue 23): one camera per pass. Bench only.

``visfly-dist bench render --backend egl-legacy`` measures it next to the batch renderer of
:mod:`visfly_dist.scene_worker.render_egl_batch`, which replaced it as the ``egl`` backend.

Depth and segmentation come from :class:`~visfly_dist.scene_worker.gl_depth_seg.DepthSegPass`: the
whole scene in one draw call, single-sampled (pixel centres), z-depth computed per fragment in
float32. RGB comes from pyrender with full materials and textures (multisampled, lit by the shared
light of :mod:`render_base` plus ambient): one mesh node per textured object, and one node for all
the untextured ones together (pyrender's cost is per node), and one node per moving obstacle, posed
at its translation on every render (depth and segmentation draw it at the same offset).

Other drones are spheres (an icosphere within 1.8% of ``drone_radius``, exact at its vertices),
culled to the view; the camera's own drone is left out of its image.

It draws in the EGL context of :func:`visfly_dist.scene_worker.render_egl.gl_context` (pyrender
only renders; its pyglet import is kept headless with ``PYGLET_HEADLESS=1``).
"""

from __future__ import annotations

import os
from typing import Sequence

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")  # must precede the first OpenGL import
os.environ.setdefault("PYGLET_HEADLESS", "1")      # pyrender imports pyglet: no X11 libraries

import numpy as np  # noqa: E402
import pyrender  # noqa: E402
import trimesh  # noqa: E402

from visfly_dist.protocol.cameras import CameraSpec  # noqa: E402
from visfly_dist.scene_worker.camera_math import camera_world_poses, gl_camera_pose, spheres_in_view  # noqa: E402
from visfly_dist.scene_worker.gl_depth_seg import DepthSegPass  # noqa: E402
from visfly_dist.scene_worker.render_common import (  # noqa: E402
    AMBIENT,
    DRONE_RGB,
    LIGHT_DIRECTION,
    SKY_RGB,
    Renderer,
    drone_segmentation_id,
)
from visfly_dist.scene_worker.render_egl import gl_context  # noqa: E402
from visfly_dist.scene_worker.shading import face_rgb  # noqa: E402
from visfly_dist.scenes.scene import Scene  # noqa: E402

RGB_FLAGS = pyrender.RenderFlags.SKIP_CULL_FACES | pyrender.RenderFlags.OFFSCREEN
LIGHT_INTENSITY = 2.0
DRONE_SUBDIVISIONS = 2   # icosphere of 320 faces: within 1.8% of the radius (4x faster than 1280 faces)


class LegacyEglRenderer(Renderer):
    """The per-camera OpenGL renderer (see the module docstring)."""

    name = "egl"

    def __init__(self, scene: Scene, cameras: Sequence[CameraSpec], drone_radius: float = 0.1) -> None:
        super().__init__(scene, cameras, drone_radius)
        self._sphere = trimesh.creation.icosphere(subdivisions=DRONE_SUBDIVISIONS, radius=max(self.drone_radius, 1e-6))
        self._sphere.visual.face_colors = [*DRONE_RGB, 255]
        self._depth_seg: DepthSegPass | None = None
        self._rgb: pyrender.Renderer | None = None
        self._rgb_scene: pyrender.Scene | None = None
        self._rgb_drones: list[pyrender.Node] = []
        self._rgb_cameras: dict[str, pyrender.Node] = {}
        self._rgb_moving: list[pyrender.Node] = []
        self._translations = np.zeros((len(scene.moving_objects), 3))

    def _move(self, translations: np.ndarray) -> None:
        """Moving objects: offsets of their draw calls (depth/segmentation) and node poses (RGB)."""
        self._translations = translations

    def _release(self) -> None:
        if self._depth_seg is None and self._rgb is None:
            return
        gl_context()
        if self._depth_seg is not None:
            self._depth_seg.delete()
        if self._rgb is not None:
            self._rgb.delete()
        self._depth_seg = self._rgb = None

    def _render(self, poses: np.ndarray, show_drones: bool) -> dict[str, np.ndarray]:
        gl_context()
        n = len(poses)
        drones = show_drones and n > 1 and self.drone_radius > 0
        centres = poses[:, :3] if drones else poses[:0, :3]
        out = {}
        for cam in self.cameras:
            origins, rots = camera_world_poses(poses, cam)
            images = np.empty((n, *cam.shape), cam.dtype)
            for a in range(n):
                pose = gl_camera_pose(origins[a], rots[a])
                in_view = spheres_in_view(cam, (centres - origins[a]) @ rots[a], self.drone_radius)
                others = in_view & (np.arange(len(centres)) != a)
                if cam.kind == "rgb":
                    images[a] = self._draw_rgb(cam, pose, centres, others)
                else:
                    depth, ids = self._pass().draw(cam, np.linalg.inv(pose), centres[others],
                                                   drone_segmentation_id(np.nonzero(others)[0]), self._translations)
                    images[a, 0] = np.where(depth > 0, depth, cam.far) if cam.kind == "depth" else ids
            out[cam.name] = images
        return out

    def _pass(self) -> DepthSegPass:
        if self._depth_seg is None:
            self._depth_seg = DepthSegPass(self.scene, (self._sphere.vertices, self._sphere.faces))
        return self._depth_seg

    def _draw_rgb(self, cam: CameraSpec, pose: np.ndarray, centres: np.ndarray, others: np.ndarray) -> np.ndarray:
        """One RGB image ``(3, H, W)`` from pyrender."""
        if self._rgb is None or self._rgb_scene is None:
            self._rgb_scene = self._build_rgb_scene()
            self._rgb = pyrender.Renderer(cam.width, cam.height)
        scene = self._rgb_scene
        camera_node = self._rgb_cameras[cam.name]
        scene.main_camera_node = camera_node
        scene.set_pose(camera_node, pose)
        for node, offset in zip(self._rgb_moving, self._translations):
            scene.set_pose(node, trimesh.transformations.translation_matrix(offset))
        while len(self._rgb_drones) < len(centres):
            self._rgb_drones.append(scene.add(pyrender.Mesh.from_trimesh(self._sphere, smooth=False)))
        for k, node in enumerate(self._rgb_drones):
            node.mesh.is_visible = k < len(centres) and bool(others[k])
            if node.mesh.is_visible:
                scene.set_pose(node, trimesh.transformations.translation_matrix(centres[k]))
        self._rgb.viewport_width, self._rgb.viewport_height = cam.width, cam.height
        colour, _ = self._rgb.render(scene, RGB_FLAGS)
        return colour.transpose(2, 0, 1)

    def _build_rgb_scene(self) -> pyrender.Scene:
        scene = pyrender.Scene(bg_color=[*(np.asarray(SKY_RGB) / 255.0), 1.0], ambient_light=[AMBIENT] * 3)
        static = self.scene.static_objects
        textured = [o.mesh for o in static if len(o.mesh.faces) and _textured(o.mesh)]
        coloured = [o.mesh for o in static if len(o.mesh.faces) and not _textured(o.mesh)]
        for obj in self.scene.moving_objects:   # one node each, posed per render
            mesh = obj.mesh
            if not _textured(mesh):
                mesh = _coloured_mesh(mesh.vertices, mesh.faces, face_rgb(obj.mesh))
            self._rgb_moving.append(scene.add(pyrender.Mesh.from_trimesh(mesh, smooth=False)))
        for mesh in textured:
            scene.add(pyrender.Mesh.from_trimesh(mesh, smooth=False))
        if coloured:  # one node for every untextured object: pyrender's cost is per node
            merged = _coloured_mesh(np.concatenate([m.triangles.reshape(-1, 3) for m in coloured]),
                                    np.arange(3 * sum(len(m.faces) for m in coloured)).reshape(-1, 3),
                                    np.concatenate([face_rgb(m) for m in coloured]))
            scene.add(pyrender.Mesh.from_trimesh(merged, smooth=False))
        z = np.asarray(LIGHT_DIRECTION)  # a directional light shines along its node's -z
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        light_pose = np.eye(4)
        light_pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
        scene.add(pyrender.DirectionalLight(color=np.ones(3), intensity=LIGHT_INTENSITY), pose=light_pose)
        for c in self.cameras:
            if c.kind == "rgb":
                self._rgb_cameras[c.name] = scene.add(pyrender.IntrinsicsCamera(
                    fx=c.focal_px, fy=c.focal_px, cx=0.5 * c.width, cy=0.5 * c.height, znear=c.near, zfar=c.far))
        return scene


def _textured(mesh: trimesh.Trimesh) -> bool:
    """Whether ``mesh`` is drawn with a texture (pyrender's own material), not face colours."""
    return mesh.visual is not None and mesh.visual.kind == "texture"


def _coloured_mesh(vertices: np.ndarray, faces: np.ndarray, face_colours: np.ndarray) -> trimesh.Trimesh:
    """A new mesh (not processed) of ``faces``, each in its colour of ``face_colours``."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert isinstance(mesh.visual, trimesh.visual.ColorVisuals), "a mesh made without a visual has colours"
    mesh.visual.face_colors = face_colours
    return mesh
