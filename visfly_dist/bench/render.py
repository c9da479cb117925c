"""``visfly-dist bench render``: renderer frames/s and obstacle queries/s, in-process and via a worker.

For each backend, resolution and sensor kind, ``agents`` drones (one camera each) at random clear
poses in a generated scene are rendered in one call; frames/s is ``agents`` over the median call's
wall time. The same is then measured "through a worker": a real ``visfly-dist worker`` process on
loopback (Zenoh, shared memory) answers ``StepRequest``s (render only), so the row includes encoding
and transport. Obstacle queries (:class:`ObstacleQueries`, same poses) are timed in-process.

The raycast backend is measured with each tracer (``native`` packets and the ``embreex`` fallback) on
1 and 2 threads. ``egl`` is the batch renderer (every camera of a call in one pass); the bench-only
backend ``egl-legacy`` is the per-camera renderer it replaced (issue 23), measured in-process only.
In-process, the configurations of one resolution and kind take turns call by call, so that their
ratios come from the same seconds. ``cpu_frames_per_s`` is frames per CPU-second of the whole
process (every thread): the per-core figure, steadier than wall time on a shared machine.

JSON rows: ``backend, tracer (raycast only), threads (raycast only), res, kind, agents, frames_per_s,
cpu_frames_per_s (in-process rows), where (in_process|worker), seconds``; one queries row
``backend="native"|"fcl", kind="queries", agents, queries_per_s, query_share_of_raycast_step``: the queries'
share of a step that renders 64x64 depth with raycast and queries (``q / (render + q)``); and the
goal rows of issues 8 and 23 (:func:`goal_rows`): ``kind="goal", goal, value, target, met``; and the
moving-obstacle rows of :mod:`visfly_dist.bench.moving` (``--moving N``, 20 by default).
"""  # noqa: E501

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

from visfly_dist.bench.common import DRONE_RADIUS, bench_poses
from visfly_dist.errors import ConfigError, RemoteError, TransportTimeoutError
from visfly_dist.output_paths import check_output_file
from visfly_dist.protocol.cameras import SENSOR_KINDS, CameraSpec

WORKER_READY_S = 120.0
WORKER_CALL_S = 600.0
QUICK_AGENTS = 20


def bench_render(backends: Sequence[str] | None = None, res: Sequence[int] = (64, 128, 256),
                 kinds: Sequence[str] = ("depth",), cameras: int = 100, reps: int = 3,
                 scene: str = "garage-stones", seed: int = 0, worker: bool = True, search_radius: float = 5.0,
                 threads: Sequence[int] = (1, 2), tracers: Sequence[str] | None = None,
                 log: Callable[[str], None] = print, moving: int = 20) -> list[dict[str, Any]]:
    """Measure every backend x resolution x kind, in-process and (if ``worker``) through a worker.

    The raycast backend is measured with each tracer (native packets, embreex) on each thread count.
    The configurations of one resolution and kind take turns, one call each per round, so their
    ratios come from the same seconds of a shared machine.

    Args:
        backends: ``raycast``, ``egl`` and/or ``egl-legacy`` (bench only); default: every available one.
        res: square resolutions, pixels per side.
        kinds: sensor kinds (``depth``, ``rgb``, ``segmentation``).
        cameras: drones rendered per call, one camera each (the rows' ``agents``).
        reps: timed calls per figure (the median counts), after one warm-up call.
        scene: generator name, rendered with ``seed``.
        worker: also measure through a real worker process.
        search_radius: the obstacle queries' search radius, metres.
        threads: raycast tracing threads to measure (the worker rows use the largest).
        tracers: raycast tracers to measure; default: ``native`` (when built) and ``embreex``.
        log: progress lines.
        moving: moving obstacles of the moving-vs-static rows (:mod:`visfly_dist.bench.moving`); 0: none.

    Returns:
        The rows described in the module docstring, then the goal rows (:func:`goal_rows`).
    """
    from visfly_dist.bench.common import time_it
    from visfly_dist.scene_worker.queries import ObstacleQueries
    from visfly_dist.scene_worker.render_base import available_backends
    from visfly_dist.scenes import generate_scene

    backends = list(backends or available_backends())
    tracers = list(tracers or available_tracers())
    _check(backends, res, kinds, cameras, reps, threads, tracers, moving)
    world = generate_scene(scene, seed=seed)
    poses = bench_poses(world, cameras, seed)
    log(f"[bench render] {scene} seed {seed}: {world.num_triangles} triangles, {len(world.objects)} objects, "
        f"{cameras} drones")
    configs: list[tuple[str, str | None, int | None]] = []
    for backend in backends:
        if backend == "raycast":
            configs += [("raycast", tracer, n) for n in threads for tracer in tracers]
        else:
            configs.append((backend, None, None))
    configs.sort(key=lambda c: c[0] == "egl-legacy")   # egl-legacy rows right after egl's (their ratio is a goal)
    if "egl" in backends:
        from visfly_dist.scene_worker.render_egl import gl_device

        log(f"[bench render] egl GL device: {gl_device().renderer}")
    rows: list[dict[str, Any]] = []
    for r in res:
        for kind in kinds:
            cam = CameraSpec(name=kind, kind=kind, width=r, height=r)
            for (backend, tracer, n), (wall, cpu) in zip(configs, _time_in_process(configs, world, cam, poses, reps)):
                rows.append(_row(backend, r, kind, cameras, wall, "in_process", tracer, n, cpu))
                log(f"[bench render] {_label(rows[-1])} {kind} {r}x{r} in-process: "
                    f"{rows[-1]['frames_per_s']:.1f} frames/s, {rows[-1]['cpu_frames_per_s']:.1f} frames/CPU-s")

    queries = ObstacleQueries(world, DRONE_RADIUS)
    tq = time_it(lambda: queries.query(poses[:, :3], search_radius), reps=max(reps, 3), warmup=1)
    render_s = _raycast_depth64_seconds(rows, world, poses, reps)
    rows.append({"backend": queries.backend, "kind": "queries", "agents": cameras, "queries_per_s": cameras / tq.median,
                 "query_share_of_raycast_step": tq.median / (tq.median + render_s) if render_s else None,
                 "where": "in_process", "seconds": tq.median})
    log(f"[bench render] obstacle queries: {rows[-1]['queries_per_s']:.0f} queries/s")
    if moving:
        from visfly_dist.bench.moving import moving_rows

        rows += moving_rows(moving, cameras, max(reps, 3), seed, 64, search_radius, log)

    if worker:
        reason = _worker_unavailable()
        if reason:
            log(f"[bench render] skipping the worker rows: {reason}")
        else:
            for backend in backends:
                if backend != LEGACY_EGL:   # bench-only: no worker serves it
                    rows += _bench_worker(backend, res, kinds, poses, scene, seed, reps, max(threads), log)
    goals = goal_rows(rows)
    for g in goals:
        log(f"[bench render] goal {g['goal']}: {g['value']:.2f} (target >= {g['target']:g}): "
            f"{'met' if g['met'] else 'NOT met'}")
    return rows + goals


def available_tracers() -> list[str]:
    """The raycast tracers usable here: ``native`` when its library loads, and ``embreex`` when installed."""
    from visfly_dist.scene_worker import render_native

    out = ["native"] if render_native.available() else []
    return out + (["embreex"] if importlib.util.find_spec("embreex") is not None else [])


LEGACY_EGL = "egl-legacy"
"""Bench-only backend: the per-camera egl renderer the batch renderer replaced (issue 23)."""

GOALS = (
    # (goal, numerator (tracer, threads, res), denominator, measure, target); issue 8's goals
    ("native / embreex per core, 64x64 depth", ("native", 1, 64), ("embreex", 1, 64), "cpu_frames_per_s", 2.5),
    ("native / embreex per core, 256x256 depth", ("native", 1, 256), ("embreex", 1, 256), "cpu_frames_per_s", 3.5),
    ("native 2 threads / 1 thread, 64x64 depth", ("native", 2, 64), ("native", 1, 64), "frames_per_s", 1.8),
    ("native 2 threads, 64x64 depth frames/s", ("native", 2, 64), None, "frames_per_s", 7000.0),
)


EGL_GOALS = (
    # (goal, kind, res, target): batch egl frames/s over the per-camera egl's, 100 cameras; issue 23's goals
    ("batch egl / per-camera egl frames/s, 64x64 depth", "depth", 64, 3.0),
    ("batch egl / per-camera egl frames/s, 64x64 rgb", "rgb", 64, 3.0),
)


def goal_rows(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Issue 8's goals as rows ``{"backend": "raycast", "kind": "goal", "goal", "value", "target", "met"}``,
    from the in-process raycast depth rows of this run, and issue 23's (``"backend": "egl"``) from its
    in-process egl and egl-legacy rows (goals whose rows are missing are left out)."""
    found = {(r["tracer"], r["threads"], r["res"]): r for r in rows
             if r.get("backend") == "raycast" and r.get("kind") == "depth" and r.get("where") == "in_process"}
    out = []
    for goal, num, den, measure, target in GOALS:
        if num not in found or (den is not None and den not in found):
            continue
        value = found[num][measure] / (found[den][measure] if den is not None else 1.0)
        out.append({"backend": "raycast", "kind": "goal", "goal": goal, "value": value, "target": target,
                    "met": bool(value >= target)})
    egl = {(r["backend"], r["kind"], r["res"]): r for r in rows
           if r.get("backend") in ("egl", LEGACY_EGL) and r.get("where") == "in_process" and "frames_per_s" in r}
    for goal, kind, res, target in EGL_GOALS:
        if ("egl", kind, res) in egl and (LEGACY_EGL, kind, res) in egl:
            value = egl[("egl", kind, res)]["frames_per_s"] / egl[(LEGACY_EGL, kind, res)]["frames_per_s"]
            out.append({"backend": "egl", "kind": "goal", "goal": goal, "value": value, "target": target,
                        "met": bool(value >= target)})
    return out


def _time_in_process(configs: Sequence[tuple[str, str | None, int | None]], world: Any, cam: CameraSpec,
                     poses: np.ndarray, reps: int) -> list[tuple[float, float]]:
    """Per configuration ``(backend, tracer, threads)``: median wall seconds and median CPU seconds
    (every thread of this process) of one render call. The configurations take turns, one call
    each per round, so that a change of load on a shared machine weighs on all of them alike."""
    from contextlib import ExitStack

    from visfly_dist.scene_worker.render_base import Renderer, make_renderer

    with ExitStack() as stack:
        renderers: list[Renderer] = []
        for backend, tracer, threads in configs:
            options = {"tracer": tracer} if tracer else {}
            if backend == LEGACY_EGL:
                from visfly_dist.scene_worker.render_egl_legacy import LegacyEglRenderer

                renderer: Renderer = LegacyEglRenderer(world, [cam], drone_radius=DRONE_RADIUS)
            else:
                renderer = make_renderer(backend, world, [cam], drone_radius=DRONE_RADIUS, threads=threads, **options)
            renderers.append(stack.enter_context(renderer))
            renderer.render(poses)
        walls: list[list[float]] = [[] for _ in renderers]
        cpus: list[list[float]] = [[] for _ in renderers]
        for _ in range(reps):
            for renderer, wall, cpu in zip(renderers, walls, cpus):
                c0, t0 = time.process_time(), time.perf_counter()
                renderer.render(poses)
                wall.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
    return [(float(np.median(w)), float(np.median(c))) for w, c in zip(walls, cpus)]


def _check(backends: Sequence[str], res: Sequence[int], kinds: Sequence[str], cameras: int, reps: int,
           threads: Sequence[int] = (1,), tracers: Sequence[str] = (), moving: int = 0) -> None:
    from visfly_dist.scene_worker.render_base import BACKENDS
    from visfly_dist.scene_worker.render_raycast import TRACERS
    from visfly_dist.scenes.generators import MAX_MOVING

    problems = [f"backend {b!r} must be one of {(*BACKENDS, LEGACY_EGL)}" for b in backends
                if b not in (*BACKENDS, LEGACY_EGL)]
    problems += [f"kind {k!r} must be one of {SENSOR_KINDS}" for k in kinds if k not in SENSOR_KINDS]
    problems += [f"res {r!r} must be an int in [1, 2048]" for r in res if not 1 <= int(r) <= 2048]
    problems += [f"threads {n!r} must be an int in [1, 64]" for n in threads if not 1 <= int(n) <= 64]
    problems += [f"tracer {t!r} must be one of {TRACERS}" for t in tracers if t not in TRACERS]
    if "raycast" in backends and not tracers:
        problems.append("no raycast tracer is available (build the native tracer or install embreex)")
    if cameras < 1 or reps < 1:
        problems.append(f"agents={cameras} and reps={reps} must be >= 1")
    if not 0 <= moving <= MAX_MOVING:  # the moving rows come last: checked before the others run
        problems.append(f"moving={moving} must be in [0, {MAX_MOVING}]")
    if problems:
        raise ConfigError("; ".join(problems))


def _row(backend: str, res: int, kind: str, agents: int, seconds: float, where: str, tracer: str | None = None,
         threads: int | None = None, cpu_seconds: float | None = None) -> dict[str, Any]:
    row = {"backend": backend, "tracer": tracer, "threads": threads, "res": int(res), "kind": kind, "agents": agents,
           "frames_per_s": agents / seconds, "where": where, "seconds": seconds}
    if cpu_seconds is not None:
        row["cpu_frames_per_s"] = agents / cpu_seconds if cpu_seconds > 0 else float("inf")
    return row


def _label(row: dict[str, Any]) -> str:
    return " ".join(str(x) for x in (row["backend"], row.get("tracer"), row.get("threads") and f"x{row['threads']}") if x)


def _raycast_depth64_seconds(rows: list[dict[str, Any]], world: Any, poses: np.ndarray, reps: int) -> float | None:
    """Seconds of one raycast 64x64 depth render of ``poses`` with the default tracer at its fastest
    thread count: from the rows, else measured now."""
    from visfly_dist.bench.common import time_it
    from visfly_dist.scene_worker.render_base import available_backends, make_renderer
    from visfly_dist.scene_worker.render_raycast import default_tracer

    tracer = default_tracer()[0]
    seconds = [row["seconds"] for row in rows if (row["backend"], row.get("tracer"), row.get("res"), row["kind"])
               == ("raycast", tracer, 64, "depth") and row["where"] == "in_process"]
    if seconds:
        return min(seconds)
    if "raycast" not in available_backends():
        return None
    with make_renderer("raycast", world, [CameraSpec(width=64, height=64)], drone_radius=DRONE_RADIUS) as r:
        return time_it(lambda: r.render(poses), reps=reps, warmup=1).median


def _worker_unavailable() -> str | None:
    if importlib.util.find_spec("visfly_dist.scene_worker.cli") is None:
        return "the worker command (visfly_dist.scene_worker.cli) is not available in this build"
    return None


def _bench_worker(backend: str, res: Sequence[int], kinds: Sequence[str], poses: np.ndarray, scene: str, seed: int,
                  reps: int, threads: int, log: Callable[[str], None]) -> list[dict[str, Any]]:
    """Rows measured through one worker process of ``backend`` (``--threads threads``, its default
    tracer); none (and a message) if it can't start."""
    from visfly_dist.protocol.session import client_of, open_session
    from visfly_dist.scene_worker.render_raycast import default_tracer

    rows = []
    tracer, threads_used = (default_tracer()[0], threads) if backend == "raycast" else (None, None)
    try:
        with _worker_process(backend, threads) as (endpoint, rpc_key):
            session = open_session(client_of([endpoint]))
            try:
                for r in res:
                    for kind in kinds:
                        cam = CameraSpec(name=kind, kind=kind, width=r, height=r)
                        seconds = _time_worker_render(session, rpc_key, cam, poses, f"gen:{scene}?seed={seed}", reps)
                        rows.append(_row(backend, r, kind, len(poses), seconds, "worker", tracer, threads_used))
                        log(f"[bench render] {_label(rows[-1])} {kind} {r}x{r} via worker: "
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
def _worker_process(backend: str, threads: int) -> Iterator[tuple[str, str]]:
    """Start ``visfly-dist worker`` on a free loopback port; yield ``(endpoint, rpc key)``; stop it."""
    from visfly_dist.protocol import keys

    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    run_id, worker_id = f"bench{os.getpid()}", f"render-{backend}"
    with tempfile.TemporaryDirectory() as root, tempfile.TemporaryFile() as err:
        argv = [sys.executable, "-m", "visfly_dist.cli", "worker", "--run-id", run_id, "--listen", endpoint,
                "--scene-root", root, "--backend", backend, "--worker-id", worker_id, "--parent-pid", str(os.getpid()),
                "--threads", str(threads)]
        proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=err,
                                start_new_session=True)
        stdout = proc.stdout
        assert stdout is not None  # stdout=PIPE
        try:
            with selectors.DefaultSelector() as sel:
                sel.register(stdout, selectors.EVENT_READ)
                line = stdout.readline().decode(errors="replace") if sel.select(WORKER_READY_S) else ""
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
            stdout.close()


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
    parser.add_argument("--backend", nargs="+", default=None, choices=("raycast", "egl", LEGACY_EGL),
                        help="backends to measure (default: every available one); egl-legacy: the per-camera "
                             "egl renderer the batch renderer replaced, in-process only, for comparison")
    parser.add_argument("--res", type=int, nargs="+", default=[64, 128, 256], help="square resolutions, pixels per side")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="raycast tracing threads to measure")
    parser.add_argument("--tracers", nargs="+", default=None, choices=("native", "embreex"),
                        help="raycast tracers to measure (default: native when built, and embreex)")
    parser.add_argument("--kinds", nargs="+", default=list(SENSOR_KINDS), choices=SENSOR_KINDS, help="sensor kinds")
    parser.add_argument("--agents", type=int, default=100, help="drones per render call, one camera each")
    parser.add_argument("--scene", default="garage-stones", help="scene generator")
    parser.add_argument("--seed", type=int, default=0, help="scene and pose seed")
    parser.add_argument("--reps", type=int, default=3, help="timed calls per figure (median)")
    parser.add_argument("--quick", action="store_true",
                        help=f"one timed call per figure, at most {QUICK_AGENTS} drones")
    parser.add_argument("--no-worker", dest="worker", action="store_false", help="skip the through-a-worker rows")
    parser.add_argument("--moving", type=int, default=20, metavar="N",
                        help="moving obstacles of the moving-vs-static rows (default 20; 0: skip them)")
    parser.add_argument("--search-radius", type=float, default=5.0, help="obstacle query search radius, metres")
    parser.add_argument("--json", metavar="FILE", help="write the rows and the machine info here")


def run(args: argparse.Namespace) -> int:
    from visfly_dist.bench import report
    from visfly_dist.bench.common import machine_info

    agents, reps = (min(args.agents, QUICK_AGENTS), 1) if args.quick else (args.agents, args.reps)
    if args.json:
        check_output_file(args.json, "--json")  # before the benchmark, not after it
    started = time.perf_counter()
    rows = bench_render(args.backend, args.res, args.kinds, agents, reps, args.scene, args.seed, args.worker,
                        args.search_radius, args.threads, args.tracers, log=lambda s: print(s, flush=True),
                        moving=args.moving)
    print(report.text_table(rows))
    print(f"[bench render] done in {time.perf_counter() - started:.1f} s")
    if args.json:
        report.write_json({"machine": machine_info(), "rows": rows}, args.json)
        print(f"wrote {args.json}")
    return 0
