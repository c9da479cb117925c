"""``visfly-dist bench step``: env-steps/s of the full ``VecEnv.step`` of a task, and where the time goes.

One env-step is one agent advanced one control step, so a ``VecEnv.step`` of ``N`` agents is ``N``
env-steps. Each measured step is the whole thing a trainer pays for: dynamics, the fan-out to the
scene workers (render and obstacle queries), gathering, noise, the task's reward and observation,
auto-resets and the numpy conversion SB3 asks for.

The stages are timed from outside the env, by wrapping (for the measurement only) the two calls a
step makes into the layers below it:

* ``physics``: ``Quadrotor.step``.
* ``render`` and ``queries``: the slowest worker's own render and query seconds, as the aggregator
  reports them in ``Observation.timings``.
* ``transport``: the rest of ``Aggregator.observe`` (request encoding, Zenoh, waiting, reply decoding
  on both sides, assembling the batch): transport including serialisation.
* ``other``: the rest of ``VecEnv.step`` (task, noise, auto-reset bookkeeping, numpy and infos).

Shares are of the timed steps' wall time and add up to 1.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from visfly_dist.errors import ConfigError

STAGES = ("physics", "transport", "render", "queries", "other")
ACTION_NOISE = 0.1
"""Std of the Gaussian noise added to the hover action: a policy near hover, with some resets."""


@dataclasses.dataclass
class StageClock:
    """Seconds spent in each stage below ``VecEnv.step``, summed over the steps it watched."""

    physics: float = 0.0
    observe: float = 0.0
    render: float = 0.0
    queries: float = 0.0
    observe_calls: int = 0

    def reset(self) -> None:
        self.physics = self.observe = self.render = self.queries = 0.0
        self.observe_calls = 0


@contextmanager
def watch_stages(env: Any) -> Iterator[StageClock]:
    """Time ``env.quad.step`` and ``env.aggregator.observe`` while the block runs, then restore them.

    The wrappers are instance attributes that shadow the bound methods and are deleted on exit, so
    the env is exactly as before afterwards.
    """
    clock = StageClock()
    quad, aggregator = env.quad, env.aggregator
    quad_step, observe = quad.step, aggregator.observe

    def timed_step(*args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return quad_step(*args, **kwargs)
        finally:
            clock.physics += time.perf_counter() - t0

    def timed_observe(*args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        try:
            obs = observe(*args, **kwargs)
        finally:
            clock.observe += time.perf_counter() - t0
            clock.observe_calls += 1
        clock.render += float(obs.timings.get("render_s", 0.0))
        clock.queries += float(obs.timings.get("query_s", 0.0))
        return obs

    quad.step = timed_step
    aggregator.observe = timed_observe
    try:
        yield clock
    finally:
        del quad.step
        del aggregator.observe


def stage_seconds(clock: StageClock, wall: float) -> dict[str, float]:
    """Seconds per stage (see the module docstring) from a clock and the steps' wall time."""
    transport = max(0.0, clock.observe - clock.render - clock.queries)
    other = max(0.0, wall - clock.physics - clock.observe)
    return {"physics": clock.physics, "transport": transport, "render": clock.render, "queries": clock.queries,
            "other": other}


def make_step_env(task: str, agents: int, workers: int, res: int, backend: str, shm: bool,
                  scenes: int | None, seed: int = 0) -> Any:
    """The task's env with ``agents`` agents in ``scenes`` scenes (default: one per worker), ``workers``
    local workers of ``backend``, and its cameras at ``res`` x ``res``.

    With ``scenes`` given, ``agents`` is rounded down to a multiple of it.
    """
    from visfly_dist import make_env
    from visfly_dist.tasks import task_class

    scenes = scenes or workers
    per_scene = agents // scenes
    if per_scene < 1:
        raise ConfigError(f"{agents=} must be at least scenes={scenes}; raise --agents or lower the scenes")
    defaults = task_class(task).config_class()
    cameras = tuple(dataclasses.replace(c, width=res, height=res) for c in defaults.cameras)
    pool = dataclasses.replace(defaults.pool, num_local_workers=workers, backend=backend, shared_memory=shm,
                               min_workers=workers)
    return make_env(task, num_envs=per_scene * scenes, agents_per_scene=per_scene, cameras=cameras, pool=pool,
                    seed=seed)


def bench_step(agents: int = 100, workers: Sequence[int] = (1, 2), res: int = 64, backend: str = "raycast",
               shm: bool = True, steps: int = 100, *, scenes: int | None = None, warmup: int = 3,
               task: str = "navigation", log: Any = None) -> list[dict[str, Any]]:
    """Measure ``VecEnv.step`` for each worker count.

    Args:
        agents: agents in the batch.
        workers: local worker counts to try, one env each.
        res: camera resolution (every camera of the task, square).
        backend: renderer of the workers: ``raycast``, ``egl`` or ``auto``.
        shm: Zenoh shared memory between the aggregator and the workers.
        steps: timed ``VecEnv.step`` calls.
        scenes: scenes loaded at once (default: one per worker).
        warmup: untimed steps first.
        task: the task name for ``make_env``.
        log: optional ``print``-like callable for progress lines.

    Returns:
        One row per worker count: ``task, agents, scenes, workers, shm, backend, res, steps,
        env_steps_per_s, step_ms, startup_s, resets, stages`` (shares of the step's wall time,
        keys :data:`STAGES`) and ``stage_ms`` (milliseconds per step).
    """
    if steps < 1 or warmup < 0:
        raise ConfigError(f"steps={steps!r} must be >= 1 and warmup={warmup!r} >= 0")
    import torch

    # The driving process runs single-threaded, as `visfly-dist train` does: with local workers on
    # the same cores, torch's second thread makes each small dynamics op wait (measured 2.5 -> 47 ms).
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    rows = []
    try:
        rows = _bench_each(task, agents, workers, res, backend, shm, steps, scenes, warmup, log)
    finally:
        torch.set_num_threads(previous_threads)
    order = ("task", "agents", "scenes", "workers", "shm", "backend", "res", "steps", "env_steps_per_s", "step_ms",
             "startup_s", "resets", "stages", "stage_ms")
    return [{k: row[k] for k in order} for row in rows]


def _bench_each(task: str, agents: int, workers: Sequence[int], res: int, backend: str, shm: bool, steps: int,
                scenes: int | None, warmup: int, log: Callable[[str], None] | None) -> list[dict[str, Any]]:
    rows = []
    for w in workers:
        if log:
            log(f"[bench step] {task}: {agents} agents, {w} worker(s), scenes={scenes or w}, shm={shm}, {res}x{res}")
        t0 = time.perf_counter()
        env = make_step_env(task, agents, w, res, backend, shm, scenes)
        try:
            startup = time.perf_counter() - t0
            rows.append(_measure(env, steps, warmup) | {
                "task": task, "agents": env.num_envs, "scenes": env.config.num_scenes, "workers": w, "shm": shm,
                "backend": backend, "res": res, "startup_s": round(startup, 2)})
        finally:
            env.close()
    return rows


def _measure(env: Any, steps: int, warmup: int) -> dict[str, Any]:
    n = env.num_envs
    rng = np.random.default_rng(0)
    hover = env.quad.hover_action().detach().cpu().numpy()

    def actions() -> np.ndarray:
        return np.clip(hover + ACTION_NOISE * rng.standard_normal((n, 4)), -1.0, 1.0).astype(np.float32)

    env.reset()
    for _ in range(warmup):
        env.step(actions())
    resets = 0
    with watch_stages(env) as clock:
        clock.reset()
        t0 = time.perf_counter()
        for _ in range(steps):
            _, _, done, _ = env.step(actions())
            resets += int(done.sum())
        wall = time.perf_counter() - t0
    seconds = stage_seconds(clock, wall)
    total = sum(seconds.values())
    return {
        "steps": steps,
        "env_steps_per_s": n * steps / wall,
        "step_ms": 1e3 * wall / steps,
        "resets": resets,
        "stages": {k: round(v / total, 4) for k, v in seconds.items()},
        "stage_ms": {k: round(1e3 * v / steps, 3) for k, v in seconds.items()},
    }


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--task", default="navigation", help="task to step (default: navigation)")
    parser.add_argument("--agents", type=int, default=100, help="agents in the batch")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="local worker counts to try")
    parser.add_argument("--scenes", type=int, default=None, help="scenes loaded at once (default: one per worker)")
    parser.add_argument("--res", type=int, default=64, help="camera resolution, pixels per side")
    parser.add_argument("--backend", default="raycast", choices=("raycast", "egl", "auto"), help="worker renderer")
    parser.add_argument("--no-shm", dest="shm", action="store_false", help="turn Zenoh shared memory off")
    parser.add_argument("--steps", type=int, default=100, help="timed VecEnv.step calls")
    parser.add_argument("--warmup", type=int, default=3, help="untimed steps first")
    parser.add_argument("--json", metavar="FILE", help="write the rows and the machine info here")


def run(args: argparse.Namespace) -> int:
    from visfly_dist.bench import report
    from visfly_dist.bench.common import machine_info

    rows = bench_step(args.agents, args.workers, args.res, args.backend, args.shm, args.steps, scenes=args.scenes,
                      warmup=args.warmup, task=args.task, log=lambda s: print(s, flush=True))
    print(report.text_table(report.flat_rows(rows)))
    if args.json:
        report.write_json({"machine": machine_info(), "rows": rows}, args.json)
        print(f"wrote {args.json}")
    return 0
