"""The peer benchmark: gym-pybullet-drones' way of simulating, with pybullet, on our scene.

What gym-pybullet-drones does, and what this module repeats (its defaults, CF2X aside):

* physics: pybullet in ``DIRECT`` mode at 240 Hz (``setTimeStep(1/240)``), control at 48 Hz, so five
  ``stepSimulation`` calls per control step. Each drone is a rigid body; before every physics step
  it reads each drone's state back (``getBasePositionAndOrientation``, ``getBaseVelocity``) and
  applies four rotor forces at the rotor positions plus one yaw torque per drone
  (``applyExternalForce`` x4, ``applyExternalTorque``), one Python call each. The drones here are
  URDF-free bodies (a cylinder collision shape) with our airframe's mass and inertia, over a plane.
* camera: ``getCameraImage`` with ``ER_TINY_RENDERER`` (pybullet's CPU rasteriser), one call per
  camera, with ``computeViewMatrix`` / ``computeProjectionMatrixFOV``; the OpenGL z-buffer is turned
  into metric depth along the optical axis, ``far * near / (far - (far - near) * z)``. The scene is
  our own mesh (exported to ``.obj``) as one static body, visual and concave-trimesh collision shape.

Departures, all to compare like with like and none changing the cost: the camera's up vector is the
body's z axis (the original keeps world z, which tilts the image of a rolled drone); the projection
uses our camera's FOV, near and far (the original: 60 deg vertical, near = arm length, far = 1000 m),
shifted by half a pixel so that TinyRenderer samples at our pixel centres.
"""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from visfly_dist.errors import ConfigError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.scene_worker.camera_math import camera_world_poses
from visfly_dist.scenes.scene import Scene

MASS = 0.46  # kg, our default airframe
INERTIA = (1.01e-3, 1.53e-3, 2.03e-3)  # kg m^2, body diagonal
ARM = 0.075  # m, X layout
KAPPA = 0.016  # yaw torque per newton of thrust
GRAVITY = 9.81
PYB_HZ = 240
CTRL_HZ = 48


def _pybullet():
    try:
        import pybullet
    except ImportError as exc:
        raise ConfigError("the peer benchmark needs pybullet: pip install 'visfly-dist[bench]' (or pybullet)") from exc
    return pybullet


def peer_physics(drones: int = 100, seconds: float = 2.0, *, seed: int = 0) -> dict[str, Any]:
    """Simulate ``drones`` hovering quadrotors for ``seconds`` of simulated time, as gym-pybullet-drones does.

    Actions are random per control step: a collective command moving the rotors' rpm by up to 5 %
    around hover (gym-pybullet-drones' RPM action range), so the drones stay upright without a
    controller; thrusts are computed batched in numpy once per control step.

    Returns:
        ``{"drones", "sim_seconds", "wall_s", "sim_seconds_per_s", "agent_steps_per_s", "physics_hz",
        "ctrl_hz", "final_mean_z"}``: ``sim_seconds_per_s`` is simulated drone-seconds per wall second
        (as in ``bench physics``); ``agent_steps_per_s`` counts physics steps
        (240 Hz) times drones.
    """
    if drones < 1 or seconds <= 0:
        raise ConfigError(f"peer_physics needs drones >= 1 and seconds > 0, got {drones=}, {seconds=}")
    p = _pybullet()
    client = p.connect(p.DIRECT)
    try:
        p.setGravity(0, 0, -GRAVITY, physicsClientId=client)
        p.setTimeStep(1.0 / PYB_HZ, physicsClientId=client)
        p.createMultiBody(0, p.createCollisionShape(p.GEOM_PLANE, physicsClientId=client), physicsClientId=client)
        shape = p.createCollisionShape(p.GEOM_CYLINDER, radius=ARM + 0.03, height=0.05, physicsClientId=client)
        side = math.ceil(math.sqrt(drones))
        ids = []
        for i in range(drones):
            body = p.createMultiBody(MASS, shape, -1, [0.5 * (i % side), 0.5 * (i // side), 1.5], [0, 0, 0, 1],
                                     physicsClientId=client)
            p.changeDynamics(body, -1, localInertiaDiagonal=list(INERTIA), linearDamping=0.0, angularDamping=0.0,
                             physicsClientId=client)
            ids.append(body)
        a = ARM / math.sqrt(2.0)
        rotors = ([a, -a, 0.0], [-a, -a, 0.0], [-a, a, 0.0], [a, a, 0.0])
        spin = np.array([-1.0, 1.0, -1.0, 1.0])  # yaw torque sign of each rotor
        hover = MASS * GRAVITY / 4.0
        rng = np.random.default_rng(seed)
        ctrl_steps = max(1, round(seconds * CTRL_HZ))
        substeps = PYB_HZ // CTRL_HZ
        state: list[Any] = [None] * drones  # pybullet (untyped) position, orientation and velocity of each drone
        t0 = time.perf_counter()
        for _ in range(ctrl_steps):
            # Thrust scales with rpm^2; actions move the rpm by up to 5 % around hover.
            thrust = hover * (1.0 + 0.05 * rng.uniform(-1.0, 1.0, (drones, 1)) * np.ones(4)) ** 2
            yaw = KAPPA * (thrust * spin).sum(axis=1)
            thrust_l = thrust.tolist()
            yaw_l = yaw.tolist()
            for _ in range(substeps):
                for k, body in enumerate(ids):
                    state[k] = (p.getBasePositionAndOrientation(body, physicsClientId=client),
                                p.getBaseVelocity(body, physicsClientId=client))
                    f = thrust_l[k]
                    for r in range(4):
                        p.applyExternalForce(body, -1, [0.0, 0.0, f[r]], rotors[r], p.LINK_FRAME, physicsClientId=client)
                    p.applyExternalTorque(body, -1, [0.0, 0.0, yaw_l[k]], p.LINK_FRAME, physicsClientId=client)
                p.stepSimulation(physicsClientId=client)
        for k, body in enumerate(ids):
            state[k] = (p.getBasePositionAndOrientation(body, physicsClientId=client),
                        p.getBaseVelocity(body, physicsClientId=client))
        wall = time.perf_counter() - t0
    finally:
        p.disconnect(client)
    sim_seconds = ctrl_steps / CTRL_HZ
    return {
        "drones": drones,
        "sim_seconds": sim_seconds,
        "wall_s": wall,
        "sim_seconds_per_s": drones * sim_seconds / wall,
        "agent_steps_per_s": drones * ctrl_steps * substeps / wall,
        "physics_hz": PYB_HZ,
        "ctrl_hz": CTRL_HZ,
        "final_mean_z": float(np.mean([s[0][0][2] for s in state])),
    }


class PeerCamera:
    """A pybullet world holding one static scene, rendering depth with TinyRenderer.

    Use as a context manager (or call :meth:`close`): it owns a pybullet ``DIRECT`` client.
    """

    def __init__(self, scene: Scene, camera: CameraSpec) -> None:
        if camera.kind != "depth":
            raise ConfigError(f"the peer camera renders depth only, got camera.kind={camera.kind!r}; use kind='depth'")
        self.camera = camera
        self._p = _pybullet()
        self._client = self._p.connect(self._p.DIRECT)
        try:
            self._load(scene)
        except BaseException:
            self.close()
            raise
        # TinyRenderer samples pixel (row i, column j) at the corner (j, i + 1) from the top left, half a
        # pixel off our pixel centres; a frustum shifted by half a pixel right and up puts its samples
        # on our centres (the same cost as the symmetric computeProjectionMatrixFOV frustum).
        f = camera.focal_px / camera.near
        half_w, half_h = 0.5 * camera.width, 0.5 * camera.height
        self._projection = self._p.computeProjectionMatrix((-half_w + 0.5) / f, (half_w + 0.5) / f,
                                                           (-half_h + 0.5) / f, (half_h + 0.5) / f,
                                                           camera.near, camera.far, physicsClientId=self._client)

    def _load(self, scene: Scene) -> None:
        p, c = self._p, self._client
        with tempfile.TemporaryDirectory(prefix="visfly-peer-") as tmp:
            path = str(Path(tmp) / "scene.obj")
            scene.combined_mesh().export(path)
            visual = p.createVisualShape(p.GEOM_MESH, fileName=path, physicsClientId=c)
            collision = p.createCollisionShape(p.GEOM_MESH, fileName=path, flags=p.GEOM_FORCE_CONCAVE_TRIMESH,
                                               physicsClientId=c)
            if visual < 0 or collision < 0:
                raise ConfigError(f"pybullet could not load the exported scene mesh {scene.name!r} "
                                  f"({scene.num_triangles} triangles)")
            p.createMultiBody(0, collision, visual, [0, 0, 0], [0, 0, 0, 1], physicsClientId=c)

    def depth(self, poses: np.ndarray) -> np.ndarray:
        """Metric depth ``(n, 1, H, W)`` float32 for drone poses ``(n, 7)`` ``[x, y, z, qw, qx, qy, qz]``."""
        p, c, cam = self._p, self._client, self.camera
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 7)
        eyes, rot = camera_world_poses(poses, cam)  # columns of rot: optical axis, left, up
        out = np.empty((len(poses), 1, cam.height, cam.width), dtype=np.float32)
        near, far = cam.near, cam.far
        for i in range(len(poses)):
            view = p.computeViewMatrix(eyes[i].tolist(), (eyes[i] + rot[i, :, 0]).tolist(), rot[i, :, 2].tolist(),
                                       physicsClientId=c)
            _, _, _, zbuf, _ = p.getCameraImage(cam.width, cam.height, view, self._projection,
                                                renderer=p.ER_TINY_RENDERER, flags=p.ER_NO_SEGMENTATION_MASK,
                                                physicsClientId=c)
            z = np.asarray(zbuf, dtype=np.float64).reshape(cam.height, cam.width)
            out[i, 0] = far * near / (far - (far - near) * z)
        return out

    def close(self) -> None:
        if self._client is not None:
            self._p.disconnect(self._client)
            self._client = None

    def __enter__(self) -> "PeerCamera":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def peer_depth(res: int = 64, cameras: int = 100, scene: Scene | None = None, *, reps: int = 2,
               seed: int = 0) -> dict[str, Any]:
    """TinyRenderer depth frames/s: ``cameras`` frames of ``res`` x ``res`` per repetition.

    Args:
        res: image width and height, pixels.
        cameras: frames per repetition (one per drone pose).
        scene: the scene; garage-stones seed 0 when None.
        reps: timed repetitions (one untimed frame warms up first); the median counts.
        seed: seed of the camera poses (clear of obstacles, as in ``bench render``).

    Returns:
        ``{"res", "cameras", "frames_per_s", "wall_s", "triangles", "scene", "renderer"}``.
    """
    if res < 1 or cameras < 1 or reps < 1:
        raise ConfigError(f"peer_depth needs res, cameras and reps >= 1, got {res=}, {cameras=}, {reps=}")
    from visfly_dist.bench.common import time_it
    from visfly_dist.bench.render import bench_poses

    if scene is None:
        from visfly_dist.scenes import generate_scene

        scene = generate_scene("garage-stones", seed=0)
    poses = bench_poses(scene, cameras, seed)  # the poses our renderers are timed at
    with PeerCamera(scene, CameraSpec(width=res, height=res)) as cam:
        cam.depth(poses[:1])
        timing = time_it(lambda: cam.depth(poses), reps=reps, warmup=0)
    return {
        "res": res,
        "cameras": cameras,
        "frames_per_s": timing.rate(cameras),
        "wall_s": sum(timing.seconds),
        "triangles": scene.num_triangles,
        "scene": scene.name,
        "renderer": "pybullet ER_TINY_RENDERER",
    }
