"""``visfly-dist bench render``: renderer frames/s and obstacle queries/s, in-process and via a worker.

For each backend, resolution and sensor kind, ``agents`` drones (one camera each) at random clear
poses in a generated scene are rendered in one call; frames/s is ``agents`` over the median call's
wall time. The same is then measured "through a worker": a real ``visfly-dist worker`` process on
loopback (Zenoh, shared memory) answers ``StepRequest``s (render only), so the row includes encoding
and transport. Obstacle queries (:class:`ObstacleQueries`, same poses) are timed in-process.

JSON rows: ``backend, res, kind, agents, frames_per_s, where (in_process|worker), seconds`` and one
queries row ``backend="fcl", kind="queries", agents, queries_per_s, query_share_of_raycast_step``:
the queries' share of a step that renders 64x64 depth with raycast and queries (``q / (render + q)``).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import selectors
import signal
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from visfly_dist.errors import ConfigError, RemoteError, TransportTimeoutError
from visfly_dist.protocol.cameras import SENSOR_KINDS, CameraSpec

DRONE_RADIUS = 0.1
CLEARANCE = 0.3
WORKER_READY_S = 120.0
WORKER_CALL_S = 600.0
QUICK_AGENTS = 20


def bench_poses(scene: Any, n: int, seed: int = 0) -> np.ndarray:
    """``n`` poses ``(n, 7)`` at least ``CLEARANCE`` from obstacles inside the scene's bounds, random yaw."""
    from visfly_dist.scene_worker.queries import ObstacleQueries

    rng = np.random.default_rng(seed)
    queries = ObstacleQueries(scene, DRONE_RADIUS)
    low, high = scene.bounds[0] + 0.3, scene.bounds[1] - 0.3
    found = np.zeros((0, 3))
    for _ in range(100):
        candidates = rng.uniform(low, high, size=(4 * n, 3))
        found = np.concatenate([found, candidates[queries.distance(candidates) > CLEARANCE]])
        if len(found) >= n:
            break
    if len(found) < n:
        raise ConfigError(f"found only {len(found)} clear poses of {n} in scene {scene.name!r}; pick another scene")
    yaw = rng.uniform(-np.pi, np.pi, n)
    quat = np.stack([np.cos(yaw / 2), np.zeros(n), np.zeros(n), np.sin(yaw / 2)], axis=1)
    return np.concatenate([found[:n], quat], axis=1)


def bench_render(backends: Sequence[str] | None = None, res: Sequence[int] = (64, 256),
                 kinds: Sequence[str] = ("depth",), cameras: int = 100, reps: int = 3,
                 scene: str = "garage-stones", seed: int = 0, worker: bool = True, search_radius: float = 5.0,
                 log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Measure every backend x resolution x kind, in-process and (if ``worker``) through a worker.

    Args:
        backends: ``raycast`` and/or ``egl``; default: every available one.
        res: square resolutions, pixels per side.
        kinds: sensor kinds (``depth``, ``rgb``, ``segmentation``).
        cameras: drones rendered per call, one camera each (the rows' ``agents``).
        reps: timed calls per figure (the median counts), after one warm-up call.
        scene: generator name, rendered with ``seed``.
        worker: also measure through a real worker process.
        search_radius: the obstacle queries' search radius, metres.
        log: progress lines.

    Returns:
        The rows described in the module docstring.
    """
    from visfly_dist.bench.common import time_it
    from visfly_dist.scene_worker.queries import ObstacleQueries
    from visfly_dist.scene_worker.render_base import available_backends, make_renderer
    from visfly_dist.scenes import generate_scene

    backends = list(backends or available_backends())
    _check(backends, res, kinds, cameras, reps)
    world = generate_scene(scene, seed=seed)
    poses = bench_poses(world, cameras, seed)
    log(f"[bench render] {scene} seed {seed}: {world.num_triangles} triangles, {len(world.objects)} objects, "
        f"{cameras} drones")
    rows: list[dict[str, Any]] = []
    for backend in backends:
        for r in res:
            for kind in kinds:
                cam = CameraSpec(name=kind, kind=kind, width=r, height=r)
                with make_renderer(backend, world, [cam], drone_radius=DRONE_RADIUS) as renderer:
                    t = time_it(lambda: renderer.render(poses), reps=reps, warmup=1)
                rows.append(_row(backend, r, kind, cameras, t.median, "in_process"))
                log(f"[bench render] {backend} {kind} {r}x{r} in-process: {rows[-1]['frames_per_s']:.1f} frames/s")

    queries = ObstacleQueries(world, DRONE_RADIUS)
    tq = time_it(lambda: queries.query(poses[:, :3], search_radius), reps=max(reps, 3), warmup=1)
    render_s = _raycast_depth64_seconds(rows, world, poses, reps)
    rows.append({"backend": "fcl", "kind": "queries", "agents": cameras, "queries_per_s": cameras / tq.median,
                 "query_share_of_raycast_step": tq.median / (tq.median + render_s) if render_s else None,
                 "where": "in_process", "seconds": tq.median})
    log(f"[bench render] obstacle queries: {rows[-1]['queries_per_s']:.0f} queries/s")

    if worker:
        reason = _worker_unavailable()
        if reason:
            log(f"[bench render] skipping the worker rows: {reason}")
        else:
            for backend in backends:
                rows += _bench_worker(backend, res, kinds, poses, scene, seed, reps, log)
    return rows


def _check(backends: Sequence[str], res: Sequence[int], kinds: Sequence[str], cameras: int, reps: int) -> None:
    from visfly_dist.scene_worker.render_base import BACKENDS

    problems = [f"backend {b!r} must be one of {BACKENDS}" for b in backends if b not in BACKENDS]
    problems += [f"kind {k!r} must be one of {SENSOR_KINDS}" for k in kinds if k not in SENSOR_KINDS]
    problems += [f"res {r!r} must be an int in [1, 2048]" for r in res if not 1 <= int(r) <= 2048]
    if cameras < 1 or reps < 1:
        problems.append(f"agents={cameras} and reps={reps} must be >= 1")
    if problems:
        raise ConfigError("; ".join(problems))


def _row(backend: str, res: int, kind: str, agents: int, seconds: float, where: str) -> dict[str, Any]:
    return {"backend": backend, "res": int(res), "kind": kind, "agents": agents, "frames_per_s": agents / seconds,
            "where": where, "seconds": seconds}


def _raycast_depth64_seconds(rows: list[dict[str, Any]], world: Any, poses: np.ndarray, reps: int) -> float | None:
    """Seconds of one raycast 64x64 depth render of ``poses``: from the rows, else measured now."""
    from visfly_dist.bench.common import time_it
    from visfly_dist.scene_worker.render_base import available_backends, make_renderer

    for row in rows:
        if (row["backend"], row["res"], row["kind"]) == ("raycast", 64, "depth"):
            return row["seconds"]
    if "raycast" not in available_backends():
        return None
    with make_renderer("raycast", world, [CameraSpec(width=64, height=64)], drone_radius=DRONE_RADIUS) as r:
        return time_it(lambda: r.render(poses), reps=reps, warmup=1).median


def _worker_unavailable() -> str | None:
    if importlib.util.find_spec("visfly_dist.scene_worker.cli") is None:
        return "the worker command (visfly_dist.scene_worker.cli) is not available in this build"
    return None


def _bench_worker(backend: str, res: Sequence[int], kinds: Sequence[str], poses: np.ndarray, scene: str, seed: int,
                  reps: int, log: Callable[[str], None]) -> list[dict[str, Any]]:
    """Rows measured through one worker process of ``backend``; none (and a message) if it can't start."""
    from visfly_dist.protocol.session import client_of, open_session

    rows = []
    try:
        with _worker_process(backend) as (endpoint, rpc_key):
            session = open_session(client_of([endpoint]))
            try:
                for r in res:
                    for kind in kinds:
                        cam = CameraSpec(name=kind, kind=kind, width=r, height=r)
                        seconds = _time_worker_render(session, rpc_key, cam, poses, f"gen:{scene}?seed={seed}", reps)
                        rows.append(_row(backend, r, kind, len(poses), seconds, "worker"))
                        log(f"[bench render] {backend} {kind} {r}x{r} via worker: "
                            f"{rows[-1]['frames_per_s']:.1f} frames/s")
            finally:
                session.close()
    except (RuntimeError, TransportTimeoutError, RemoteError) as exc:
        log(f"[bench render] skipping the {backend} worker rows: {exc}")
    return rows


def _time_worker_render(session: Any, rpc_key: str, cam: CameraSpec, poses: np.ndarray, source: str,
                        reps: int) -> float:
    """Median seconds of a render-only StepRequest of ``poses`` in a scene loaded for ``cam``."""
    from visfly_dist.bench.common import time_it
    from visfly_dist.protocol.messages import LoadScene, ScenePoses, StepRequest, UnloadScene

    key = f"{cam.kind}{cam.width}"
    _call(session, rpc_key, LoadScene(key, source, (cam,), DRONE_RADIUS).to_message())
    step = StepRequest((ScenePoses(key, poses),), render=True, query=False).to_message()
    try:
        return time_it(lambda: _call(session, rpc_key, step), reps=reps, warmup=1).median
    finally:
        _call(session, rpc_key, UnloadScene(key).to_message())


@contextmanager
def _worker_process(backend: str) -> Iterator[tuple[str, str]]:
    """Start ``visfly-dist worker`` on a free loopback port; yield ``(endpoint, rpc key)``; stop it."""
    from visfly_dist.protocol import keys

    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    run_id, worker_id = f"bench{os.getpid()}", f"render-{backend}"
    with tempfile.TemporaryDirectory() as root, tempfile.TemporaryFile() as err:
        argv = [sys.executable, "-m", "visfly_dist.cli", "worker", "--run-id", run_id, "--listen", endpoint,
                "--scene-root", root, "--backend", backend, "--worker-id", worker_id, "--parent-pid", str(os.getpid())]
        proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=err,
                                start_new_session=True)
        try:
            with selectors.DefaultSelector() as sel:
                sel.register(proc.stdout, selectors.EVENT_READ)
                line = proc.stdout.readline().decode(errors="replace") if sel.select(WORKER_READY_S) else ""
            if "ready" not in line:
                err.seek(0)
                tail = err.read().decode(errors="replace")[-1500:]
                raise RuntimeError(f"worker did not start (exit {proc.poll()}, stdout {line!r}): {tail}")
            yield endpoint, keys.worker_rpc(run_id, worker_id)
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(15)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
            proc.stdout.close()


def _free_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _call(session: Any, key: str, message: dict[str, Any]) -> dict[str, Any]:
    """One request/reply; the decoded reply, or RemoteError / TransportTimeoutError."""
    import zenoh

    from visfly_dist.protocol.codec import decode, encode

    replies = list(session.get(key, payload=encode(message), timeout=WORKER_CALL_S,
                               consolidation=zenoh.ConsolidationMode.NONE))
    if not replies:
        raise TransportTimeoutError(f"no reply from {key} within {WORKER_CALL_S} s")
    reply = replies[0]
    if reply.ok is None:
        err = decode(reply.err.payload.to_bytes())
        raise RemoteError(key, str(err.get("error")), str(err.get("message")))
    return decode(reply.ok.payload.to_bytes())


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--backend", nargs="+", default=None, choices=("raycast", "egl"),
                        help="backends to measure (default: every available one)")
    parser.add_argument("--res", type=int, nargs="+", default=[64, 256], help="square resolutions, pixels per side")
    parser.add_argument("--kinds", nargs="+", default=list(SENSOR_KINDS), choices=SENSOR_KINDS, help="sensor kinds")
    parser.add_argument("--agents", type=int, default=100, help="drones per render call, one camera each")
    parser.add_argument("--scene", default="garage-stones", help="scene generator")
    parser.add_argument("--seed", type=int, default=0, help="scene and pose seed")
    parser.add_argument("--reps", type=int, default=3, help="timed calls per figure (median)")
    parser.add_argument("--quick", action="store_true",
                        help=f"one timed call per figure, at most {QUICK_AGENTS} drones")
    parser.add_argument("--no-worker", dest="worker", action="store_false", help="skip the through-a-worker rows")
    parser.add_argument("--search-radius", type=float, default=5.0, help="obstacle query search radius, metres")
    parser.add_argument("--json", metavar="FILE", help="write the rows and the machine info here")


def run(args: argparse.Namespace) -> int:
    from visfly_dist.bench import report
    from visfly_dist.bench.common import machine_info

    agents, reps = (min(args.agents, QUICK_AGENTS), 1) if args.quick else (args.agents, args.reps)
    started = time.perf_counter()
    rows = bench_render(args.backend, args.res, args.kinds, agents, reps, args.scene, args.seed, args.worker,
                        args.search_radius, log=lambda s: print(s, flush=True))
    print(report.text_table(rows))
    print(f"[bench render] done in {time.perf_counter() - started:.1f} s")
    if args.json:
        report.write_json({"machine": machine_info(), "rows": rows}, args.json)
        print(f"wrote {args.json}")
    return 0
