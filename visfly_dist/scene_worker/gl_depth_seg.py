"""An exact depth + segmentation pass in raw OpenGL, for the ``egl`` backend.

pyrender draws one node per object with several uniform uploads each, which on llvmpipe costs more
than the rasterising, and its depth buffer is 24-bit and multisampled. This pass draws the whole
scene with one indexed draw call into a single-sample framebuffer (so every pixel is sampled at its
centre) whose one ``RG32F`` attachment receives, per pixel, the eye-space z-depth computed in the
fragment shader (exact in float32, no depth-buffer quantisation) and the object id.

It needs a current OpenGL >= 3.3 core context (the caller's), and leaves the draw framebuffer bound.
"""

from __future__ import annotations

import ctypes

import numpy as np
from OpenGL import GL

from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.scenes.scene import Scene

VERTEX_SHADER = """
#version 330 core
layout(location = 0) in vec3 position;
layout(location = 1) in float object_id;
uniform mat4 view;          // world -> OpenGL eye frame
uniform mat4 proj;
uniform vec3 offset;        // translation of the mesh drawn (drones); zero for the scene
uniform float id_override;  // >= 0: every vertex gets this id
out float eye_depth;
flat out float seg_id;
void main() {
    vec4 eye = view * vec4(position + offset, 1.0);
    eye_depth = -eye.z;
    seg_id = id_override >= 0.0 ? id_override : object_id;
    gl_Position = proj * eye;
}
"""

FRAGMENT_SHADER = """
#version 330 core
in float eye_depth;
flat in float seg_id;
layout(location = 0) out vec2 value;
void main() {
    value = vec2(eye_depth, seg_id);
}
"""


def projection(camera: CameraSpec) -> np.ndarray:
    """The OpenGL projection matrix of a pinhole camera with square pixels, centred."""
    f, w, h, n, far = camera.focal_px, camera.width, camera.height, camera.near, camera.far
    return np.array([
        [2.0 * f / w, 0.0, 0.0, 0.0],
        [0.0, 2.0 * f / h, 0.0, 0.0],
        [0.0, 0.0, -(far + n) / (far - n), -2.0 * far * n / (far - n)],
        [0.0, 0.0, -1.0, 0.0],
    ])


class _Geometry:
    """An indexed triangle mesh in a vertex array: positions and a per-vertex id."""

    def __init__(self, vertices: np.ndarray, ids: np.ndarray, faces: np.ndarray) -> None:
        data = np.concatenate([vertices, ids[:, None]], axis=1).astype(np.float32)
        self.count = int(faces.size)
        self.vao = GL.glGenVertexArrays(1)
        self.vbo, self.ebo = GL.glGenBuffers(2)
        GL.glBindVertexArray(self.vao)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self.vbo)
        GL.glBufferData(GL.GL_ARRAY_BUFFER, data.nbytes, data, GL.GL_STATIC_DRAW)
        GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, self.ebo)
        GL.glBufferData(GL.GL_ELEMENT_ARRAY_BUFFER, faces.nbytes, np.ascontiguousarray(faces, np.uint32), GL.GL_STATIC_DRAW)
        GL.glEnableVertexAttribArray(0)
        GL.glVertexAttribPointer(0, 3, GL.GL_FLOAT, GL.GL_FALSE, 16, ctypes.c_void_p(0))
        GL.glEnableVertexAttribArray(1)
        GL.glVertexAttribPointer(1, 1, GL.GL_FLOAT, GL.GL_FALSE, 16, ctypes.c_void_p(12))
        GL.glBindVertexArray(0)

    def draw(self) -> None:
        GL.glBindVertexArray(self.vao)
        GL.glDrawElements(GL.GL_TRIANGLES, self.count, GL.GL_UNSIGNED_INT, ctypes.c_void_p(0))

    def delete(self) -> None:
        GL.glDeleteVertexArrays(1, [self.vao])
        GL.glDeleteBuffers(2, [self.vbo, self.ebo])


class DepthSegPass:
    """Draws the scene (and drone spheres) into z-depth and object-id images.

    Args:
        scene: the static scene; its triangles are uploaded once.
        drone: a drone's mesh ``(vertices, faces)`` centred on the origin, or ``None``.
    """

    def __init__(self, scene: Scene, drone: tuple[np.ndarray, np.ndarray] | None) -> None:
        self._program = _link(VERTEX_SHADER, FRAGMENT_SHADER)
        self._uniforms = {name: GL.glGetUniformLocation(self._program, name)
                          for name in ("view", "proj", "offset", "id_override")}
        objects = [o for o in scene.objects if len(o.mesh.faces)]
        self._scene = None
        if objects:
            starts = np.cumsum([0] + [len(o.mesh.vertices) for o in objects])
            self._scene = _Geometry(
                np.concatenate([o.mesh.vertices for o in objects]),
                np.concatenate([np.full(len(o.mesh.vertices), o.object_id, np.float32) for o in objects]),
                np.concatenate([o.mesh.faces + s for o, s in zip(objects, starts)]))
        self._drone = None if drone is None else _Geometry(drone[0], np.zeros(len(drone[0]), np.float32), drone[1])
        self._targets: dict[tuple[int, int], tuple[int, int, int]] = {}

    def draw(self, camera: CameraSpec, view: np.ndarray, drones: np.ndarray, drone_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Render one camera.

        Args:
            camera: intrinsics and clip planes.
            view: ``(4, 4)`` world -> OpenGL-eye matrix of the camera.
            drones: ``(k, 3)`` centres of the drone spheres to draw.
            drone_ids: ``(k,)`` their segmentation ids.

        Returns:
            ``(depth (H, W) float32, 0 where nothing; ids (H, W) uint16)``, row 0 at the top.
        """
        w, h = camera.width, camera.height
        GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, self._target(w, h)[0])
        GL.glViewport(0, 0, w, h)
        GL.glDisable(GL.GL_MULTISAMPLE)
        GL.glDisable(GL.GL_CULL_FACE)
        GL.glDisable(GL.GL_BLEND)
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthMask(GL.GL_TRUE)
        GL.glDepthFunc(GL.GL_LESS)
        GL.glClearColor(0.0, 0.0, 0.0, 0.0)
        GL.glClear(GL.GL_COLOR_BUFFER_BIT | GL.GL_DEPTH_BUFFER_BIT)
        GL.glUseProgram(self._program)
        u = self._uniforms
        GL.glUniformMatrix4fv(u["view"], 1, GL.GL_TRUE, view.astype(np.float32))
        GL.glUniformMatrix4fv(u["proj"], 1, GL.GL_TRUE, projection(camera).astype(np.float32))
        GL.glUniform3f(u["offset"], 0.0, 0.0, 0.0)
        GL.glUniform1f(u["id_override"], -1.0)
        if self._scene is not None:
            self._scene.draw()
        if self._drone is not None:
            for centre, drone_id in zip(drones, drone_ids):
                GL.glUniform3f(u["offset"], *(float(c) for c in centre))
                GL.glUniform1f(u["id_override"], float(drone_id))
                self._drone.draw()
        GL.glBindVertexArray(0)
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._target(w, h)[0])
        GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0)
        values = np.empty((h, w, 2), np.float32)
        GL.glReadPixels(0, 0, w, h, GL.GL_RG, GL.GL_FLOAT, values)
        values = values[::-1]
        return values[..., 0].copy(), values[..., 1].astype(np.uint16)

    def delete(self) -> None:
        """Free the GL objects (the context must be current)."""
        for fbo, colour, depth in self._targets.values():
            GL.glDeleteFramebuffers(1, [fbo])
            GL.glDeleteRenderbuffers(2, [colour, depth])
        self._targets.clear()
        for geometry in (self._scene, self._drone):
            if geometry is not None:
                geometry.delete()
        GL.glDeleteProgram(self._program)

    def _target(self, w: int, h: int) -> tuple[int, int, int]:
        """The framebuffer of one resolution (made on first use)."""
        if (w, h) not in self._targets:
            colour, depth = GL.glGenRenderbuffers(2)
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, colour)
            GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_RG32F, w, h)
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, depth)
            GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_DEPTH_COMPONENT24, w, h)
            fbo = GL.glGenFramebuffers(1)
            GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, fbo)
            GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_RENDERBUFFER, colour)
            GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, GL.GL_RENDERBUFFER, depth)
            status = GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER)
            assert status == GL.GL_FRAMEBUFFER_COMPLETE, f"framebuffer {w}x{h} incomplete: {status}"
            self._targets[(w, h)] = (fbo, colour, depth)
        return self._targets[(w, h)]


def _link(vertex: str, fragment: str) -> int:
    program = GL.glCreateProgram()
    shaders = []
    for kind, source in ((GL.GL_VERTEX_SHADER, vertex), (GL.GL_FRAGMENT_SHADER, fragment)):
        shader = GL.glCreateShader(kind)
        GL.glShaderSource(shader, source)
        GL.glCompileShader(shader)
        assert GL.glGetShaderiv(shader, GL.GL_COMPILE_STATUS), GL.glGetShaderInfoLog(shader)
        GL.glAttachShader(program, shader)
        shaders.append(shader)
    GL.glLinkProgram(program)
    assert GL.glGetProgramiv(program, GL.GL_LINK_STATUS), GL.glGetProgramInfoLog(program)
    for shader in shaders:
        GL.glDeleteShader(shader)
    return program
