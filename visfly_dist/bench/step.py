"""``visfly-dist bench step``: env-steps/s of the full ``VecEnv.step`` of a task, and where the time goes.

One env-step is one agent advanced one control step, so a ``VecEnv.step`` of ``N`` agents is ``N``
env-steps. Each measured step is the whole thing a trainer pays for: dynamics, the fan-out to the
scene workers (render and obstacle queries), gathering, noise, the task's reward and observation,
auto-resets and the numpy conversion SB3 asks for.

Two ways to run it: a sweep over worker counts (``--agents``, ``--workers``, ``--scenes``; what
``bench all`` uses), or named rows (``--rows``, see :data:`ROWS` and :data:`GROUPS`): the training
layout (one agent per scene, 16 and 64 envs) against the one-scene layout (100 agents in one
scene), a reset-heavy step against the same step without resets, remote workers behind an added
network delay (:mod:`visfly_dist.bench.remote`), and the step overhead at 1,024 agents in 256 scenes.
The reset row and the no-reset row are measured together, their envs stepped in turns
(:data:`INTERLEAVED`), so that their ratio is not the machine's load moving between two runs.

Stages. When the env reports its own ``step_timings`` (seconds of the last step: ``physics_s``,
``render_s``, ``query_s``, ``transport_s``, ...), those are used. Otherwise they are timed from
outside, by wrapping (for the measurement only) the two calls a step makes into the layers below:

* ``physics``: ``Quadrotor.step``.
* ``render`` and ``queries``: the slowest worker's own render and query seconds, as the aggregator
  reports them in ``Observation.timings``.
* ``transport``: the rest of ``Aggregator.observe`` (request encoding, Zenoh, waiting, reply decoding
  on both sides, assembling the batch): transport including serialisation.
* ``other``: the rest of ``VecEnv.step`` (task, noise, auto-reset bookkeeping, numpy and infos).

Shares are of the timed steps' wall time and add up to 1. ``overhead_ms`` is the step's wall time
outside rendering, queries and physics, per step: transport plus other.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import time
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

from visfly_dist.bench.common import STAGES
from visfly_dist.errors import ConfigError
from visfly_dist.output_paths import check_output_file

ACTION_NOISE = 0.1
"""Std of the Gaussian noise added to the hover action: a policy near hover, with some resets."""

STEP_TIMING_KEYS = {"physics": "physics_s", "transport": "transport_s", "render": "render_s", "queries": "query_s"}
"""Stage -> key of ``env.step_timings``, for envs that time their own steps."""


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


@contextlib.contextmanager
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


def reported_timings(env: Any) -> Mapping[str, float] | None:
    """The env's own ``step_timings`` of its last step, when it has them (None otherwise)."""
    timings = getattr(env, "step_timings", None)
    return timings if isinstance(timings, Mapping) and timings else None


@dataclasses.dataclass(frozen=True)
class RowSpec:
    """One named row of ``bench step --rows``.

    Attributes:
        name: the row's name in tables and JSON.
        agents: agents in the batch (``num_envs``).
        scenes: scenes loaded at once (``agents / scenes`` agents per scene).
        max_episode_steps: episode length (``None``: the task's default).
        delay_ms: ``None``: local workers over shared memory; a number: remote workers (plain TCP,
            no shared memory) behind this much added round trip.
        what: one line for the README and the table.
    """

    name: str
    agents: int
    scenes: int
    max_episode_steps: int | None = None
    delay_ms: float | None = None
    what: str = ""


ROW_STARTUP_TIMEOUT_S = 900.0
"""Scene-load deadline of the named rows: a worker loads its 32 to 128 scenes in one request, which
takes minutes on a loaded 2-core machine (the default 60 s drops every worker, again and again)."""

ROW_STEP_TIMEOUT_S = 120.0
"""Step deadline of the named rows: a step of 1,024 agents renders 512 frames per worker."""

NO_RESETS = 1_000_000
"""``max_episode_steps`` of the no-reset row: longer than any measurement."""

ROWS: dict[str, RowSpec] = {r.name: r for r in (
    RowSpec("train16", 16, 16, what="training layout: 16 envs, one agent per scene"),
    RowSpec("train64", 64, 64, what="training layout: 64 envs, one agent per scene"),
    RowSpec("one_scene", 100, 1, what="one-scene layout: 100 agents in one scene"),
    RowSpec("resets", 16, 16, max_episode_steps=10, what="train16, every agent resets every 10 steps"),
    RowSpec("no_resets", 16, 16, max_episode_steps=NO_RESETS, what="train16 without time-limit resets"),
    RowSpec("delay0", 16, 16, delay_ms=0, what="train16, remote workers behind the proxy, 0 ms added"),
    RowSpec("delay5", 16, 16, delay_ms=5, what="train16, remote workers, 5 ms added round trip"),
    RowSpec("delay20", 16, 16, delay_ms=20, what="train16, remote workers, 20 ms added round trip"),
    RowSpec("overhead", 1024, 256, what="1,024 agents in 256 scenes: overhead outside render and physics"),
)}
"""The named rows of issue 13's figures."""

INTERLEAVED = ("resets", "no_resets")
"""Rows measured together, their envs stepped in turns, when both are asked for: their ratio is a goal
of a few percent, less than the load on a shared machine moves between two rows measured one after the other."""
INTERLEAVE_BLOCK = 10
"""Steps an env takes before the other's turn: one episode of the reset row."""

GROUPS: dict[str, tuple[str, ...]] = {
    "layout": ("train16", "train64", "one_scene"),
    "resets": ("resets", "no_resets"),
    "latency": ("delay0", "delay5", "delay20"),
    "overhead": ("overhead",),
}
GROUPS["all"] = tuple(name for group in GROUPS.values() for name in group)

RATIOS: tuple[tuple[str, str, str, str, str], ...] = (
    # (name, numerator row, denominator row, figure, goal)
    ("train16 / one_scene env-steps/s", "train16", "one_scene", "env_steps_per_s", ">= 0.8"),
    ("resets / no_resets ms per step", "resets", "no_resets", "step_ms", "<= 1.15"),
    ("delay5 / delay0 env-steps/s", "delay5", "delay0", "env_steps_per_s", ""),
    ("delay20 / delay0 env-steps/s", "delay20", "delay0", "env_steps_per_s", ""),
)


def expand_rows(names: Sequence[str]) -> list[RowSpec]:
    """Row names and group names -> the rows, in order, each once.

    Raises:
        ConfigError: an unknown name (the message lists the valid ones).
    """
    out: list[str] = []
    for name in names:
        if name in GROUPS:
            out += [n for n in GROUPS[name] if n not in out]
        elif name in ROWS:
            out += [name] if name not in out else []
        else:
            raise ConfigError(f"unknown bench step row {name!r}; valid rows: {sorted(ROWS)}, groups: {sorted(GROUPS)}")
    return [ROWS[n] for n in out]


def make_step_env(task: str, agents: int, workers: int, res: int, backend: str, shm: bool,
                  scenes: int | None, seed: int = 0, *, pool: Callable[[Any], Any] | None = None,
                  rows_timeouts: bool = False, **env_kwargs: Any) -> Any:
    """The task's env with ``agents`` agents in ``scenes`` scenes (default: one per worker), ``workers``
    local workers of ``backend``, and its cameras at ``res`` x ``res``.

    With ``scenes`` given, ``agents`` is rounded down to a multiple of it. ``pool``, if given, turns
    the resulting ``PoolConfig`` into the one to use (remote workers); ``rows_timeouts`` raises the
    pool's deadlines to :data:`ROW_STARTUP_TIMEOUT_S` / :data:`ROW_STEP_TIMEOUT_S`; ``env_kwargs``
    go to ``make_env``.
    """
    from visfly_dist import make_env
    from visfly_dist.tasks import task_class

    scenes = scenes or workers
    per_scene = agents // scenes
    if per_scene < 1:
        raise ConfigError(f"{agents=} must be at least scenes={scenes}; raise --agents or lower the scenes")
    defaults = task_class(task).config_class()
    cameras = tuple(dataclasses.replace(c, width=res, height=res) for c in defaults.cameras)
    pool_cfg = dataclasses.replace(defaults.pool, num_local_workers=workers, backend=backend, shared_memory=shm,
                                   min_workers=workers)
    if rows_timeouts:
        pool_cfg = dataclasses.replace(pool_cfg, startup_timeout_s=max(pool_cfg.startup_timeout_s, ROW_STARTUP_TIMEOUT_S),
                                       step_timeout_s=max(pool_cfg.step_timeout_s, ROW_STEP_TIMEOUT_S))
    if pool is not None:
        pool_cfg = pool(pool_cfg)
    return make_env(task, num_envs=per_scene * scenes, agents_per_scene=per_scene, cameras=cameras, pool=pool_cfg,
                    seed=seed, **env_kwargs)


@contextlib.contextmanager
def single_threaded_torch() -> Iterator[None]:
    """Run the block with one torch thread, as ``visfly-dist train`` does: with local workers on the
    same cores, torch's second thread makes each small dynamics op wait (measured 2.5 -> 47 ms)."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


ROW_ORDER = ("row", "task", "agents", "scenes", "workers", "delay_ms", "shm", "backend", "res", "steps",
             "env_steps_per_s", "step_ms", "overhead_ms", "startup_s", "resets", "stages", "stage_ms", "timings")


def _ordered(row: Mapping[str, Any]) -> dict[str, Any]:
    return {k: row[k] for k in ROW_ORDER if k in row}


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
        env_steps_per_s, step_ms, overhead_ms, startup_s, resets, stages`` (shares of the step's
        wall time, keys :data:`STAGES`), ``stage_ms`` (milliseconds per step) and ``timings``
        (``env`` when the env timed its own stages, ``wrapped`` otherwise).
    """
    _check_counts(steps, warmup)
    rows = []
    with single_threaded_torch():
        for w in workers:
            if log:
                log(f"[bench step] {task}: {agents} agents, {w} worker(s), scenes={scenes or w}, shm={shm}, {res}x{res}")
            t0 = time.perf_counter()
            env = make_step_env(task, agents, w, res, backend, shm, scenes)
            try:
                startup = time.perf_counter() - t0
                rows.append(measure_steps(env, steps, warmup) | {
                    "task": task, "agents": env.num_envs, "scenes": env.config.num_scenes, "workers": w, "shm": shm,
                    "backend": backend, "res": res, "startup_s": round(startup, 2)})
            finally:
                env.close()
    return [_ordered(r) for r in rows]


def bench_rows(rows: Sequence[RowSpec], steps: int = 100, warmup: int = 3, *, workers: int = 2, res: int = 64,
               backend: str = "raycast", overhead_steps: int | None = None, task: str = "navigation",
               log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Measure the named rows (:data:`ROWS`) and the ratios between them (:data:`RATIOS`).

    Args:
        rows: the rows, e.g. ``expand_rows(["layout", "resets"])``.
        steps: timed ``VecEnv.step`` calls per row.
        warmup: untimed steps first.
        workers: scene workers of every row (local ones, or remote ones for the delay rows).
        res: camera resolution.
        backend: the workers' renderer.
        overhead_steps: timed steps of the ``overhead`` row (default: ``steps``; its steps are long).
        task: the task name.
        log: optional ``print``-like callable for progress lines.

    Returns:
        ``{"rows": [...], "ratios": [...]}``: rows as :func:`bench_step` returns them plus ``row``
        and ``delay_ms``; ratios ``{"ratio", "value", "goal"}`` for each pair of rows measured.
    """
    _check_counts(steps, warmup)
    out = []
    with single_threaded_torch():
        together = [spec for spec in rows if spec.name in INTERLEAVED]
        for spec in rows:
            n = overhead_steps if spec.name == "overhead" and overhead_steps else steps
            if spec in together and len(together) > 1:
                if spec is together[0]:
                    if log:
                        log(f"[bench step] {' and '.join(s.name for s in together)}, in turns of {INTERLEAVE_BLOCK} "
                            f"steps: {'; '.join(s.what for s in together)} ({workers} workers, {res}x{res}, {n} steps each)")
                    out += [_ordered(r) for r in _measure_rows_interleaved(together, n, warmup, workers, res, backend, task)]
                continue
            if log:
                log(f"[bench step] {spec.name}: {spec.what} ({workers} workers, {res}x{res}, {n} steps)")
            with _row_env(spec, workers, res, backend, task) as (env, fields):
                out.append(_ordered(measure_steps(env, n, warmup) | fields))
    by_name = {r["row"]: r for r in out}
    ratios = [{"ratio": name, "value": round(by_name[a][fig] / by_name[b][fig], 3), "goal": goal}
              for name, a, b, fig, goal in RATIOS if a in by_name and b in by_name]
    if "overhead" in by_name:
        row = by_name["overhead"]
        ratios.append({"ratio": f"overhead ms per step at {row['agents']:,} agents in {row['scenes']} scenes",
                       "value": row["overhead_ms"], "goal": "<= 2"})
    return {"rows": out, "ratios": ratios}


@contextlib.contextmanager
def _row_env(spec: RowSpec, workers: int, res: int, backend: str, task: str) -> Iterator[tuple[Any, dict[str, Any]]]:
    """The env of a row (and its remote workers behind the proxy, for the delay rows), and the row's
    fixed fields; closed on exit."""
    from visfly_dist.bench.remote import RemoteWorkers

    kwargs = {} if spec.max_episode_steps is None else {"max_episode_steps": spec.max_episode_steps}
    with contextlib.ExitStack() as stack:
        remote = None
        if spec.delay_ms is not None:
            remote = RemoteWorkers(workers, spec.delay_ms, backend)
            stack.callback(remote.close)
        t0 = time.perf_counter()
        try:
            env = make_step_env(task, spec.agents, workers, res, backend, remote is None, spec.scenes,
                                pool=remote.pool if remote else None, rows_timeouts=True, **kwargs)
        except Exception as exc:
            if remote is not None:
                raise RuntimeError(f"{spec.name}: the env did not start with remote workers; their logs:\n"
                                   f"{remote.log_tail()}") from exc
            raise
        stack.callback(env.close)
        yield env, {"row": spec.name, "task": task, "agents": spec.agents, "scenes": spec.scenes, "workers": workers,
                    "delay_ms": spec.delay_ms, "shm": remote is None, "backend": backend, "res": res,
                    "startup_s": round(time.perf_counter() - t0, 2)}


def _measure_rows_interleaved(specs: Sequence[RowSpec], steps: int, warmup: int, workers: int, res: int,
                              backend: str, task: str) -> list[dict[str, Any]]:
    """Rows whose ratio is a goal, measured with their envs open together and stepped in turns."""
    with contextlib.ExitStack() as stack:
        opened = [stack.enter_context(_row_env(spec, workers, res, backend, task)) for spec in specs]
        rows = measure_interleaved([env for env, _ in opened], steps, warmup, INTERLEAVE_BLOCK)
        return [row | fields for row, (_, fields) in zip(rows, opened)]


def _check_counts(steps: int, warmup: int) -> None:
    if not isinstance(steps, int) or steps < 1 or not isinstance(warmup, int) or warmup < 0:
        raise ConfigError(f"steps={steps!r} must be an int >= 1 and warmup={warmup!r} an int >= 0")


def measure_steps(env: Any, steps: int, warmup: int) -> dict[str, Any]:
    """Reset ``env``, take ``warmup`` untimed steps, then time ``steps`` steps of a noisy hover policy
    (each step's ``env.step`` call; drawing the actions is not timed).

    Stages come from ``env.step_timings`` when the env reported them during the warm-up, else from
    :func:`watch_stages`; the row's ``timings`` says which (``env`` or ``wrapped``).
    """
    meter = StepMeter(env, warmup)
    if meter.reported:
        meter.run(steps)
        return meter.row()
    resets, wall = 0, 0.0
    with watch_stages(env) as clock:
        clock.reset()
        for _ in range(steps):
            actions = meter.actions()
            t0 = time.perf_counter()
            _, _, done, _ = env.step(actions)
            wall += time.perf_counter() - t0
            resets += int(done.sum())
    return _row(steps, env.num_envs, wall, resets, stage_seconds(clock, wall), "wrapped")


class StepMeter:
    """Times the steps of one env a block at a time, so that two envs can be measured interleaved.

    Construction resets the env and takes ``warmup`` untimed steps; :attr:`reported` says whether the
    env times its own steps (``step_timings``), which :meth:`run` needs.
    """

    def __init__(self, env: Any, warmup: int) -> None:
        self.env = env
        self._rng = np.random.default_rng(0)
        self._hover = env.quad.hover_action().detach().cpu().numpy()
        env.reset()
        for _ in range(warmup):
            env.step(self.actions())
        self.reported = bool(warmup) and reported_timings(env) is not None
        self.steps, self.wall, self.resets = 0, 0.0, 0
        self.seconds = dict.fromkeys(STEP_TIMING_KEYS, 0.0)

    def actions(self) -> np.ndarray:
        """A noisy hover action for every agent."""
        noise = ACTION_NOISE * self._rng.standard_normal((self.env.num_envs, 4))
        return np.clip(self._hover + noise, -1.0, 1.0).astype(np.float32)

    def run(self, steps: int) -> None:
        """Time ``steps`` more steps, adding the env's own stage timings."""
        for _ in range(steps):
            actions = self.actions()  # the policy's time is not the env's
            t0 = time.perf_counter()
            _, _, done, _ = self.env.step(actions)
            self.wall += time.perf_counter() - t0
            self.resets += int(done.sum())
            timings = reported_timings(self.env) or {}
            for stage, key in STEP_TIMING_KEYS.items():
                self.seconds[stage] += float(timings.get(key, 0.0))
        self.steps += steps

    def row(self) -> dict[str, Any]:
        """The figures of the steps timed so far (``timings``: ``env``)."""
        seconds = {stage: self.seconds[stage] for stage in STAGES if stage != "other"}
        seconds["other"] = max(0.0, self.wall - sum(seconds.values()))
        return _row(self.steps, self.env.num_envs, self.wall, self.resets, {k: seconds[k] for k in STAGES}, "env")


def measure_interleaved(envs: Sequence[Any], steps: int, warmup: int, block: int) -> list[dict[str, Any]]:
    """:func:`measure_steps` of several envs, taking turns ``block`` steps at a time, so that every
    env's figures come from the same stretch of time: their ratios are not skewed by the machine's
    load moving between them. Envs that do not time their own steps are measured one after another."""
    meters = [StepMeter(env, warmup) for env in envs]
    if not all(m.reported for m in meters):
        return [measure_steps(env, steps, 0) for env in envs]
    done, turn = 0, 0
    while done < steps:
        n = min(block, steps - done)
        for meter in meters if turn % 2 == 0 else meters[::-1]:  # neither always goes first
            meter.run(n)
        done, turn = done + n, turn + 1
    return [m.row() for m in meters]


def _row(steps: int, agents: int, wall: float, resets: int, seconds: Mapping[str, float], source: str) -> dict[str, Any]:
    total = sum(seconds.values())
    stage_ms = {k: round(1e3 * v / steps, 3) for k, v in seconds.items()}
    return {
        "steps": steps,
        "env_steps_per_s": agents * steps / wall,
        "step_ms": 1e3 * wall / steps,
        "overhead_ms": round(stage_ms["transport"] + stage_ms["other"], 3),
        "resets": resets,
        "stages": {k: round(v / total, 4) for k, v in seconds.items()},
        "stage_ms": stage_ms,
        "timings": source,
    }


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rows", nargs="+", metavar="ROW",
                        help=f"named rows instead of the worker sweep: rows {', '.join(ROWS)}; groups "
                             f"{', '.join(GROUPS)}")
    parser.add_argument("--quick", action="store_true", help="fewer steps (20; 5 for the overhead row)")
    parser.add_argument("--task", default="navigation", help="task to step (default: navigation)")
    parser.add_argument("--agents", type=int, default=100, help="sweep: agents in the batch")
    parser.add_argument("--workers", type=int, nargs="+", default=None,
                        help="sweep: local worker counts to try (default 1 2); rows: one count (default 2)")
    parser.add_argument("--scenes", type=int, default=None, help="sweep: scenes loaded at once (default: one per worker)")
    parser.add_argument("--res", type=int, default=64, help="camera resolution, pixels per side")
    parser.add_argument("--backend", default="raycast", choices=("raycast", "egl", "auto"), help="worker renderer")
    parser.add_argument("--no-shm", dest="shm", action="store_false", help="sweep: turn Zenoh shared memory off")
    parser.add_argument("--steps", type=int, default=None, help="timed VecEnv.step calls (default 100; --quick 20)")
    parser.add_argument("--warmup", type=int, default=3, help="untimed steps first")
    parser.add_argument("--json", metavar="FILE", help="write the rows and the machine info here")


def run(args: argparse.Namespace) -> int:
    from visfly_dist.bench import report
    from visfly_dist.bench.common import load_average, machine_info

    def log(line: str) -> None:
        print(line, flush=True)

    steps = (20 if args.quick else 100) if args.steps is None else args.steps
    problems = [f"--{name} {value} must be >= 1" for name, value in (("steps", steps), ("scenes", args.scenes))
                if value is not None and value < 1]
    problems += [f"--workers {w} must be >= 1" for w in args.workers or () if w < 1]
    if args.warmup < 0:
        problems.append(f"--warmup {args.warmup} must be >= 0")
    if problems:
        raise ConfigError("; ".join(problems))
    if args.json:
        check_output_file(args.json, "--json")  # before the benchmark, not after it
    result: dict[str, Any] = {"machine": machine_info()}
    if args.rows:
        if args.workers is not None and len(args.workers) != 1:
            raise ConfigError(f"--workers {args.workers} with --rows takes one count, e.g. --workers 2")
        out = bench_rows(expand_rows(args.rows), steps, args.warmup, workers=(args.workers or [2])[0], res=args.res,
                         backend=args.backend, overhead_steps=5 if args.quick and not args.steps else None,
                         task=args.task, log=log)
        result |= out
        flat = report.flat_rows(out["rows"])
        print(report.text_table(flat, report.columns_of(flat, skip=[f"stage_ms.{s}" for s in STAGES])))
        if out["ratios"]:
            print(report.text_table(out["ratios"]))
    else:
        result["rows"] = bench_step(args.agents, args.workers or [1, 2], args.res, args.backend, args.shm, steps,
                                    scenes=args.scenes, warmup=args.warmup, task=args.task, log=log)
        print(report.text_table(report.flat_rows(result["rows"])))
    result["load_average_end"] = load_average()
    if args.json:
        report.write_json(result, args.json)
        print(f"wrote {args.json}")
    return 0
