"""An exact depth + segmentation pass in raw OpenGL, for the ``egl`` backend.

pyrender draws one node per object with several uniform uploads each, which on llvmpipe costs more
than the rasterising, and its depth buffer is 24-bit and multisampled. This pass draws the whole
scene with one indexed draw call (every drone with one instanced call, and each moving obstacle
with a one-instance call at its offset) into a single-sample
framebuffer, so every pixel is sampled at its centre. Its one ``RG32F`` attachment receives, per
pixel, the eye-space z-depth computed in the fragment shader (exact in float32, no depth-buffer
quantisation) and the object id.

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
layout(location = 2) in vec3 offset;    // per drone instance; the scene reads the constant 0
uniform mat4 view;                      // world -> OpenGL eye frame
uniform mat4 proj;
out float eye_depth;
flat out float seg_id;
void main() {
    vec4 eye = view * vec4(position + offset, 1.0);
    eye_depth = -eye.z;
    seg_id = object_id;
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
    """An indexed triangle mesh in a vertex array: positions and a per-vertex id, or (``instanced``)
    positions only, drawn once per instance with an ``(offset, id)`` from an instance buffer."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, ids: np.ndarray | None) -> None:
        instanced = ids is None
        data = np.ascontiguousarray(vertices if ids is None else np.concatenate([vertices, ids[:, None]], axis=1),
                                    dtype=np.float32)
        stride = data.shape[1] * 4
        self.count = int(faces.size)
        self.vao = GL.glGenVertexArrays(1)
        self.vbo, self.ebo, self.instances = GL.glGenBuffers(3)
        GL.glBindVertexArray(self.vao)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self.vbo)
        GL.glBufferData(GL.GL_ARRAY_BUFFER, data.nbytes, data, GL.GL_STATIC_DRAW)
        GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, self.ebo)
        indices = np.ascontiguousarray(faces, np.uint32)
        GL.glBufferData(GL.GL_ELEMENT_ARRAY_BUFFER, indices.nbytes, indices, GL.GL_STATIC_DRAW)
        GL.glEnableVertexAttribArray(0)
        GL.glVertexAttribPointer(0, 3, GL.GL_FLOAT, GL.GL_FALSE, stride, ctypes.c_void_p(0))
        if instanced:   # offset xyz and id per instance
            GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self.instances)
            GL.glEnableVertexAttribArray(2)
            GL.glVertexAttribPointer(2, 3, GL.GL_FLOAT, GL.GL_FALSE, 16, ctypes.c_void_p(0))
            GL.glVertexAttribDivisor(2, 1)
            GL.glEnableVertexAttribArray(1)
            GL.glVertexAttribPointer(1, 1, GL.GL_FLOAT, GL.GL_FALSE, 16, ctypes.c_void_p(12))
            GL.glVertexAttribDivisor(1, 1)
        else:
            GL.glEnableVertexAttribArray(1)
            GL.glVertexAttribPointer(1, 1, GL.GL_FLOAT, GL.GL_FALSE, stride, ctypes.c_void_p(12))
        GL.glBindVertexArray(0)

    def draw(self, instances: np.ndarray | None = None) -> None:
        """Draw once, or once per row ``[x, y, z, id]`` of ``instances``."""
        GL.glBindVertexArray(self.vao)
        if instances is None:
            GL.glVertexAttrib3f(2, 0.0, 0.0, 0.0)   # the offset attribute is off: its constant
            GL.glDrawElements(GL.GL_TRIANGLES, self.count, GL.GL_UNSIGNED_INT, ctypes.c_void_p(0))
        elif len(instances):
            data = np.ascontiguousarray(instances, dtype=np.float32)
            GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self.instances)
            GL.glBufferData(GL.GL_ARRAY_BUFFER, data.nbytes, data, GL.GL_STREAM_DRAW)
            GL.glDrawElementsInstanced(GL.GL_TRIANGLES, self.count, GL.GL_UNSIGNED_INT, ctypes.c_void_p(0), len(data))

    def delete(self) -> None:
        GL.glDeleteVertexArrays(1, [self.vao])
        GL.glDeleteBuffers(3, [self.vbo, self.ebo, self.instances])


class DepthSegPass:
    """Draws the scene (and drone spheres) into z-depth and object-id images.

    Args:
        scene: the static scene; its triangles are uploaded once.
        drone: a drone's mesh ``(vertices, faces)`` centred on the origin, or ``None``.
    """

    def __init__(self, scene: Scene, drone: tuple[np.ndarray, np.ndarray] | None) -> None:
        self._program = _link(VERTEX_SHADER, FRAGMENT_SHADER)
        self._uniforms = {name: GL.glGetUniformLocation(self._program, name) for name in ("view", "proj")}
        objects = [o for o in scene.static_objects if len(o.mesh.faces)]
        self._moving = [(_Geometry(o.mesh.vertices, o.mesh.faces, None), o.object_id) for o in scene.moving_objects]
        self._scene = None
        if objects:
            starts = np.cumsum([0] + [len(o.mesh.vertices) for o in objects])
            self._scene = _Geometry(
                np.concatenate([o.mesh.vertices for o in objects]),
                np.concatenate([o.mesh.faces + s for o, s in zip(objects, starts)]),
                np.concatenate([np.full(len(o.mesh.vertices), o.object_id, np.float32) for o in objects]))
        self._drone = None if drone is None else _Geometry(drone[0], drone[1], None)
        self._targets: dict[tuple[int, int], tuple[int, int, int]] = {}

    def draw(self, camera: CameraSpec, view: np.ndarray, drones: np.ndarray,
             drone_ids: np.ndarray, moving: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Render one camera.

        Args:
            camera: intrinsics and clip planes.
            view: ``(4, 4)`` world -> OpenGL-eye matrix of the camera.
            drones: ``(k, 3)`` centres of the drone spheres to draw.
            drone_ids: ``(k,)`` their segmentation ids.
            moving: ``(m, 3)`` translations of the scene's moving objects (scene order); None: 0.

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
        if self._scene is not None:
            self._scene.draw()
        for k, (geometry, object_id) in enumerate(self._moving):   # one instance each, at its offset
            offset = np.zeros(3) if moving is None else moving[k]
            geometry.draw(np.array([[*offset, object_id]]))
        if self._drone is not None and len(drones):
            self._drone.draw(np.concatenate([drones, np.asarray(drone_ids)[:, None]], axis=1))
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
        for geometry in (self._scene, self._drone, *(g for g, _ in self._moving)):
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
