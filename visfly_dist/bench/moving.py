"""The cost of moving obstacles: one scene rendered and queried with N moving stones vs the same
scene with every stone static where it stands (``visfly-dist bench render --moving N``).

The moving scene is ``garage-stones`` with ``moving=N``; the static one is its :meth:`Scene.at_time`
copy (the same triangles, no motion). Each rep renders ``agents`` 64x64 depth cameras with the
default raycast tracer and queries obstacles for them, first in the static scene, then in the
moving one at a new time (so every moving call really moves the obstacles: new instance transforms
and a top-level commit, or a fresh moving-object BVH with embreex), alternating so that both see
the same minute of a shared machine. Medians of the reps count.

Rows ``{"backend": "raycast", "tracer", "kind": "moving", "moving": N, "res", "agents", "static_s",
"moving_s", "overhead", "where": "moving_vs_static"}`` for ``what`` = ``render`` and ``render+queries`` (``overhead`` =
``moving_s / static_s - 1``), and a goal row: render+queries overhead under 10%.
"""

from __future__ import annotations

import time
from typing import Any, Callable

import numpy as np

from visfly_dist.protocol.cameras import CameraSpec

GOAL_OVERHEAD = 0.10
WHERE = "moving_vs_static"   # the rows' ``where``: in-process, this comparison only
INSTANTS = 4     # the moving scene cycles through these instants, one static copy each
INSTANT_S = 0.25   # seconds between two instants


def moving_rows(moving: int, agents: int, reps: int, seed: int = 0, res: int = 64, search_radius: float = 5.0,
                log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Measure the moving-obstacle overhead (module docstring); ``[]`` when raycast is unavailable."""
    from visfly_dist.bench.common import DRONE_RADIUS, bench_poses
    from visfly_dist.scene_worker.queries import ObstacleQueries
    from visfly_dist.scene_worker.render_base import available_backends, make_renderer
    from visfly_dist.scene_worker.render_raycast import RaycastRenderer
    from visfly_dist.scenes import generate_scene

    if "raycast" not in available_backends():
        log("[bench render] skipping the moving-obstacle rows: no raycast backend")
        return []
    world = generate_scene("garage-stones", seed=seed, moving=moving)
    poses = bench_poses(world.at_time(0.0), agents, seed)
    cam = CameraSpec(width=res, height=res)
    timings: dict[tuple[str, str], list[float]] = {(s, w): [] for s in ("static", "moving") for w in ("render", "queries")}
    instants = [k * INSTANT_S for k in range(INSTANTS)]
    statics = [world.at_time(t) for t in instants]   # each instant, every object static (built untimed)
    renderers = [make_renderer("raycast", scene, [cam], DRONE_RADIUS) for scene in [world, *statics]]
    try:
        queries = [ObstacleQueries(scene, DRONE_RADIUS) for scene in [world, *statics]]
        assert isinstance(renderers[0], RaycastRenderer)  # what make_renderer("raycast", ...) builds
        tracer = renderers[0].tracer
        for rep in range(reps + INSTANTS):   # the first round warms every renderer up
            k = rep % INSTANTS
            pair = [("static", renderers[1 + k], queries[1 + k]), ("moving", renderers[0], queries[0])]
            for name, renderer, query in (pair if rep % 2 else pair[::-1]):
                t0 = time.process_time()
                renderer.render(poses, time=instants[k])
                t1 = time.process_time()
                query.query(poses[:, :3], search_radius, time=instants[k])
                t2 = time.process_time()
                if rep >= INSTANTS:
                    timings[(name, "render")].append(t1 - t0)
                    timings[(name, "queries")].append(t2 - t1)
    finally:
        for renderer in renderers:
            renderer.close()
    med = {key: float(np.median(v)) for key, v in timings.items()}
    rows: list[dict[str, Any]] = []
    for what, parts in (("render", ("render",)), ("render+queries", ("render", "queries"))):
        s = sum(med[("static", p)] for p in parts)
        m = sum(med[("moving", p)] for p in parts)
        rows.append({"backend": "raycast", "tracer": tracer, "kind": "moving", "what": what, "moving": moving,
                     "res": res, "agents": agents, "static_s": s, "moving_s": m, "overhead": m / s - 1.0,
                     "where": WHERE})
        log(f"[bench render] {moving} moving obstacles, {what}, {agents} x {res}x{res} depth ({tracer}): "
            f"static {1e3 * s:.2f} CPU-ms, moving {1e3 * m:.2f} CPU-ms, overhead {100 * rows[-1]['overhead']:+.1f}%")
    value = rows[-1]["overhead"]
    rows.append({"backend": "raycast", "kind": "goal", "goal": f"{moving} moving obstacles: render+queries overhead",
                 "value": value, "target": GOAL_OVERHEAD, "met": bool(value < GOAL_OVERHEAD), "where": WHERE})
    return rows
