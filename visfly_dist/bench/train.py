"""``visfly-dist bench train``: the default training loop for a fixed budget, and who is busy when.

One run is :func:`visfly_dist.training.ppo.train` with the task's default ``TrainConfig`` (only the
budget, the seed and a temporary run folder changed; no checkpoints). It reports:

* ``env_steps_per_s``: env steps of the whole training loop (rollouts and PPO updates) per second
  of its wall time, from the start to the end of the learning loop (env start-up excluded);
* ``rollout_env_steps_per_s``: env steps per second of rollout collection alone;
* ``learner_busy``: CPU seconds of the training process over the loop's wall time (1.0 = one core
  busy throughout; more with several torch threads);
* ``workers_busy``: CPU seconds of the scene worker processes (from ``/proc/<pid>/stat``) over the
  loop's wall time times the number of workers (1.0 = every worker busy throughout);
* ``learner_cpu_s_per_1k``: CPU seconds of the training process (every thread: Zenoh's included;
  not the benchmark's own sampler of the workers' CPU) during rollout collection per 1,000 rollout
  env steps, *outside the policy network* (the policy's forward passes timed on their thread and
  taken out): the serial part of the learner that caps scaling; ``policy_cpu_s_per_1k`` is the
  part taken out. It is split into ``learner_cpu_main_s_per_1k`` (the trainer's own thread: the env
  core, the aggregator, the trainer's bookkeeping) and ``learner_cpu_threads_s_per_1k`` (every other
  thread of the process: Zenoh's network threads, torch's intra-op pool).
* ``startup_s``: from the ``train()`` call to the trainer's first ``learn`` (workers, scenes, the
  env and the model); ``teardown_s``: from the end of ``learn`` to the end of the call (the final
  save, the workers stopped).

Runs follow the host plan (:mod:`visfly_dist.training.host_plan`) unless ``--device``,
``--num-envs`` or ``--workers`` say otherwise; ``--algo ppo sb3-ppo`` runs both trainers in one go
and adds their ratios. The default window (49,152 env steps) includes navigation's scene swaps, as
the main job's steady state does.

Loop, rollout and update seconds come from the trainer's ``summary`` (``loop_s``, ``rollout_s``,
``update_s``) when it reports them; otherwise they are timed by wrapping, for the measurement only,
SB3's ``OnPolicyAlgorithm.learn`` and ``collect_rollouts`` and ``PPO.train`` (``timing`` in the row
says which). When neither is available the loop is the whole ``train()`` call, start-up included.

With ``--delay-ms``, each run uses remote workers (plain TCP) behind that much added round trip
(:mod:`visfly_dist.bench.remote`), and each delay's figures are divided by the 0 ms run's.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import shutil
import tempfile
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Iterator, Mapping, Sequence

from visfly_dist.errors import ConfigError

DEFAULT_TIMESTEPS = 49_152
QUICK_TIMESTEPS = 4096
_CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


def process_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of process ``pid`` (None when it is gone)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(fields[11]) + int(fields[12])) / _CLOCK_TICKS  # utime, stime: fields 14 and 15 of stat


def worker_children(root: int | None = None) -> list[int]:
    """Pids of the ``visfly-dist worker`` processes descending from ``root`` (default: this process),
    whether the trainer started them itself or through a launcher process."""
    root = os.getpid() if root is None else root
    children: dict[int, list[int]] = {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat", "rb") as f:
                ppid = int(f.read().rsplit(b")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(name))
    out, todo = [], list(children.get(root, ()))
    while todo:
        pid = todo.pop()
        todo += children.get(pid, ())
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                argv = f.read().split(b"\0")
        except OSError:
            continue
        if b"visfly_dist.cli" in argv and b"worker" in argv:
            out.append(pid)
    return sorted(out)


@dataclass(frozen=True)
class CpuSnapshot:
    """Wall clock, this process's CPU seconds and each worker's CPU seconds at one moment."""

    wall: float
    learner_cpu: float
    workers: dict[int, float]


class CpuMonitor:
    """Keeps the last CPU seconds seen of every worker child, sampling every ``period_s``.

    Workers can be gone (reaped) by the time a run ends; the sampler thread keeps their last value.
    Its own scans of ``/proc`` run in the training process: :meth:`learner_cpu_s` leaves them out.
    """

    def __init__(self, period_s: float = 0.25) -> None:
        self._last: dict[int, float] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._period_s = period_s
        self._thread = threading.Thread(target=self._sample_loop, daemon=True, name="bench-cpu-monitor")
        self._thread.start()

    def _sample(self) -> dict[int, float]:
        for pid in worker_children():
            cpu = process_cpu_s(pid)
            if cpu is not None:
                with self._lock:
                    self._last[pid] = cpu
        with self._lock:
            return dict(self._last)

    def _sample_loop(self) -> None:
        while not self._stop.wait(self._period_s):
            self._sample()

    def learner_cpu_s(self) -> float:
        """CPU seconds of this process (every thread) but the sampler's own."""
        ident = self._thread.ident
        assert ident is not None, "the sampler thread is started in __init__"
        return time.process_time() - time.clock_gettime(time.pthread_getcpuclockid(ident))

    def snapshot(self) -> CpuSnapshot:
        """Now: wall clock, this process's CPU (the sampler's left out), every worker's CPU (the last
        seen for exited ones)."""
        workers = self._sample()
        return CpuSnapshot(time.perf_counter(), self.learner_cpu_s(), workers)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


@dataclass
class LoopClock:
    """Seconds of SB3's learning loop, rollouts and updates, and CPU snapshots at the loop's ends."""

    rollout_s: float = 0.0
    update_s: float = 0.0
    start: CpuSnapshot | None = None
    end: CpuSnapshot | None = None
    rollouts: int = 0
    updates: int = 0
    rollout_cpu_s: float = 0.0
    rollout_main_cpu_s: float = 0.0  # the collecting thread's own share of rollout_cpu_s
    policy_cpu_s: float = 0.0
    learn_began: float | None = None  # perf_counter when the first trainer's learn began (start-up before it)
    learn_ended: float | None = None  # and when the last one returned (the final save and shut-down after it)
    _depth: int = field(default=0, repr=False)


@contextlib.contextmanager
def watch_trainers(snapshot: Callable[[], CpuSnapshot],
                   learner_cpu: Callable[[], float] = time.process_time) -> Iterator[LoopClock]:
    """While the block runs, time SB3's ``learn``, ``collect_rollouts`` and ``PPO.train``, and the
    process CPU of rollout collection (SB3's and :class:`TensorPPO`'s; ``learner_cpu``: the
    process's CPU seconds) with the policy's forward passes in it (their thread's CPU time); then
    restore every method."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
    from stable_baselines3.common.policies import ActorCriticPolicy

    from visfly_dist.training.tensor_ppo import TensorPPO

    clock = LoopClock()
    learn, collect, update = OnPolicyAlgorithm.learn, OnPolicyAlgorithm.collect_rollouts, PPO.train
    tensor_collect, tensor_learn = TensorPPO.collect, TensorPPO.learn
    forward, predict_values = ActorCriticPolicy.forward, ActorCriticPolicy.predict_values

    def learn_span(method: Callable[..., Any]) -> Callable[..., Any]:
        def timed(self: Any, *args: Any, **kwargs: Any) -> Any:
            if clock.learn_began is None:
                clock.learn_began = time.perf_counter()
            try:
                return method(self, *args, **kwargs)
            finally:
                clock.learn_ended = time.perf_counter()
        return timed

    def timed_learn(self: Any, *args: Any, **kwargs: Any) -> Any:
        clock._depth += 1
        if clock._depth == 1:
            clock.start = snapshot()
        try:
            return learn(self, *args, **kwargs)
        finally:
            clock._depth -= 1
            if clock._depth == 0:
                clock.end = snapshot()

    def cpu_of(method: Callable[..., Any], count: bool) -> Callable[..., Any]:
        def timed(self: Any, *args: Any, **kwargs: Any) -> Any:
            t0, c0, m0 = time.perf_counter(), learner_cpu(), time.thread_time()
            try:
                return method(self, *args, **kwargs)
            finally:
                clock.rollout_cpu_s += learner_cpu() - c0
                clock.rollout_main_cpu_s += time.thread_time() - m0
                if count:
                    clock.rollout_s += time.perf_counter() - t0
                    clock.rollouts += 1
        return timed

    def policy_cpu(method: Callable[..., Any]) -> Callable[..., Any]:
        def timed(self: Any, *args: Any, **kwargs: Any) -> Any:
            c0 = time.thread_time()
            try:
                return method(self, *args, **kwargs)
            finally:
                clock.policy_cpu_s += time.thread_time() - c0
        return timed

    def timed_update(self: Any, *args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return update(self, *args, **kwargs)
        finally:
            clock.update_s += time.perf_counter() - t0
            clock.updates += 1

    saved = [(OnPolicyAlgorithm, "learn", learn), (OnPolicyAlgorithm, "collect_rollouts", collect), (PPO, "train", update),
             (TensorPPO, "collect", tensor_collect), (ActorCriticPolicy, "forward", forward),
             (ActorCriticPolicy, "predict_values", predict_values)]
    saved.append((TensorPPO, "learn", tensor_learn))
    patches = [(OnPolicyAlgorithm, "learn", learn_span(timed_learn)),
               (OnPolicyAlgorithm, "collect_rollouts", cpu_of(collect, True)), (PPO, "train", timed_update),
               (TensorPPO, "collect", cpu_of(tensor_collect, False)), (TensorPPO, "learn", learn_span(tensor_learn)),
               (ActorCriticPolicy, "forward", policy_cpu(forward)),
               (ActorCriticPolicy, "predict_values", policy_cpu(predict_values))]
    for owner, name, replacement in patches:
        setattr(owner, name, replacement)
    try:
        yield clock
    finally:
        for owner, name, method in saved:
            setattr(owner, name, method)


def busy_shares(start: CpuSnapshot, end: CpuSnapshot) -> dict[str, Any]:
    """Learner CPU / wall, and workers' CPU / (wall x workers), between two snapshots."""
    wall = max(end.wall - start.wall, 1e-9)
    pids = sorted(end.workers)
    worker_cpu = sum(end.workers[p] - start.workers.get(p, 0.0) for p in pids)
    return {"learner_busy": round((end.learner_cpu - start.learner_cpu) / wall, 3),
            "workers_busy": round(worker_cpu / (wall * len(pids)), 3) if pids else None,
            "worker_processes": len(pids)}


def default_workers(task: str) -> int:
    """The task's default number of scene workers (its ``PoolConfig.num_local_workers``)."""
    from visfly_dist.tasks import task_class

    return task_class(task).config_class().pool.num_local_workers


def train_once(task: str, timesteps: int, delay_ms: float | None = None, workers: int | None = None,
               seed: int = 0, changes: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """One default training run of ``timesteps`` env steps; ``delay_ms``: remote workers behind that delay.

    ``changes`` are ``TrainConfig`` fields to change from the default (the figures are meant for the
    default; tests use it for tiny sizes).

    Returns:
        The row: ``task, delay_ms, workers, timesteps, env_steps_per_s, rollout_env_steps_per_s,
        loop_s, rollout_s, update_s, update_share, learner_busy, workers_busy, startup_s, teardown_s,
        success_rate, timing, overlap`` (whether the run trained with ``--overlap``).
    """
    import torch

    from visfly_dist.bench.remote import RemoteWorkers
    from visfly_dist.training.config import TrainConfig
    from visfly_dist.training.ppo import train

    count = workers
    out_dir = tempfile.mkdtemp(prefix="visfly-bench-train-")
    threads = torch.get_num_threads()
    monitor = CpuMonitor()
    printed = io.StringIO()
    remote = None
    try:
        if delay_ms is not None:
            count = default_workers(task) if count is None else count
            remote = RemoteWorkers(count, delay_ms, backend="raycast")
        overrides = {} if remote is None else {"pool": {"listen": [f"tcp/127.0.0.1:{remote.listen_port}"],
                                                        "shared_memory": False, "min_workers": count}}
        cfg = TrainConfig(task=task, timesteps=timesteps, seed=seed, out=out_dir, checkpoint_every=0,
                          progress=False, workers=count if remote is None else 0,
                          run_id=remote.run_id if remote else None, overrides=overrides)
        cfg = replace(cfg, **(changes or {}))
        with watch_trainers(monitor.snapshot, monitor.learner_cpu_s) as clock, contextlib.redirect_stdout(printed):
            before = monitor.snapshot()
            result = train(cfg)
            after = monitor.snapshot()
    except Exception as exc:
        if remote is None:
            raise
        raise RuntimeError(f"bench train ({task}, delay_ms={delay_ms}) failed: {exc}\n"
                           f"{printed.getvalue()[-2000:]}\n{remote.log_tail()}") from exc
    finally:
        monitor.close()
        torch.set_num_threads(threads)
        if remote is not None:
            remote.close()
        shutil.rmtree(out_dir, ignore_errors=True)
    config = result.config
    assert config is not None  # train() returns the config it trained with
    row = _row(task, delay_ms, count if remote is not None else config.workers, result, clock, before, after)
    return {**row, "algo": config.algo, "device": config.device, "num_envs": config.num_envs,
            "worker_threads": config.worker_threads, "overlap": bool(config.overlap),
            "host_plan": config.host_plan.get("reasons", {})}


def _row(task: str, delay_ms: float | None, workers: int | None, result: Any, clock: LoopClock, before: CpuSnapshot,
         after: CpuSnapshot) -> dict[str, Any]:
    summary = dict(result.summary)
    if "rollout_s" in summary and "update_s" in summary:
        timing, rollout_s, update_s = "trainer summary", float(summary["rollout_s"]), float(summary["update_s"])
    elif clock.rollouts:
        timing, rollout_s, update_s = "sb3 wrapped", clock.rollout_s, clock.update_s
    else:
        timing, rollout_s, update_s = "train() only", float("nan"), float("nan")
    start, end = (clock.start, clock.end) if clock.start and clock.end else (before, after)
    loop_s = float(summary.get("loop_s", end.wall - start.wall))
    steps = int(result.timesteps)
    per_1k = 1000.0 / steps if steps else float("nan")
    return {
        "task": task, "delay_ms": delay_ms, "workers": workers, "timesteps": steps,
        "env_steps_per_s": round(steps / loop_s, 1),
        "rollout_env_steps_per_s": round(steps / rollout_s, 1) if rollout_s > 0 else None,
        "loop_s": round(loop_s, 2), "rollout_s": round(rollout_s, 2), "update_s": round(update_s, 2),
        "update_share": round(update_s / loop_s, 3),
        **busy_shares(start, end),
        # from the call to the first learn (env, workers, scenes, model); the final save and shut-down are apart
        "startup_s": round((clock.learn_began or after.wall) - before.wall - (0.0 if clock.learn_began else loop_s), 2),
        "teardown_s": round(after.wall - clock.learn_ended, 2) if clock.learn_ended else None,
        "success_rate": summary.get("success_rate"),
        "learner_cpu_s_per_1k": round((clock.rollout_cpu_s - clock.policy_cpu_s) * per_1k, 4),
        "learner_cpu_main_s_per_1k": round((clock.rollout_main_cpu_s - clock.policy_cpu_s) * per_1k, 4),
        "learner_cpu_threads_s_per_1k": round((clock.rollout_cpu_s - clock.rollout_main_cpu_s) * per_1k, 4),
        "policy_cpu_s_per_1k": round(clock.policy_cpu_s * per_1k, 4),
        "timing": timing if clock.start or "loop_s" in summary else f"{timing}; loop = whole train() call",
    }


def bench_train(task: str = "navigation", timesteps: int = DEFAULT_TIMESTEPS, delays: Sequence[float] | None = None,
                workers: int | None = None, seed: int = 0, *, algos: Sequence[str | None] = (None,),
                changes: Mapping[str, Any] | None = None, log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run the default training loop once per trainer and delay (``None``: local workers).

    ``algos``: the trainers (``ppo``, ``sb3-ppo``; ``None``: the task's default). ``changes``:
    ``TrainConfig`` fields to change from the default (see :func:`train_once`).

    Returns:
        ``{"rows": [...], "ratios": [...]}``; ratios divide each delayed run's whole-loop and
        rollout env-steps/s by the 0 ms run's (same trainer), and ``ppo``'s figures by
        ``sb3-ppo``'s (same delay) when both ran.
    """
    if not isinstance(timesteps, int) or timesteps < 1:
        raise ConfigError(f"timesteps={timesteps!r} must be an int >= 1")
    if workers is not None and (not isinstance(workers, int) or workers < 1):
        raise ConfigError(f"workers={workers!r} must be an int >= 1")
    rows = []
    for algo in algos:
        for delay in (list(delays) if delays else [None]):
            if log:
                where = "local workers" if delay is None else f"remote workers behind {delay:g} ms added round trip"
                log(f"[bench train] {task} ({algo or 'default trainer'}): {timesteps:,} env steps, {where}")
            run_changes = dict(changes or {}) | ({"algo": algo} if algo else {})
            rows.append(train_once(task, timesteps, delay, workers, seed, run_changes))
    return {"rows": rows, "ratios": delay_ratios(rows) + trainer_ratios(rows)}


def delay_ratios(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Each delayed run's env-steps/s over the same trainer's 0 ms run."""
    out = []
    for r in rows:
        base = next((b for b in rows if b["delay_ms"] == 0 and b["algo"] == r["algo"]), None)
        if base is None or r is base or r["delay_ms"] is None:
            continue
        for fig in ("env_steps_per_s", "rollout_env_steps_per_s"):
            if r[fig] and base[fig]:
                out.append({"ratio": f"{r['algo']} delay {r['delay_ms']:g} / 0 ms {fig}", "value": round(r[fig] / base[fig], 3),
                            "goal": ">= 0.9" if fig == "env_steps_per_s" and r["delay_ms"] == 20 else ""})
    return out


def trainer_ratios(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """``ppo`` over ``sb3-ppo`` at the same delay: env-steps/s (whole loop, rollout) and learner CPU.

    Each ``ppo`` run is paired with the ``sb3-ppo`` run nearest to it in the run order (the one
    before it on a tie), so an interleaved order (``--algo sb3-ppo ppo ppo sb3-ppo``) pairs runs
    made under the same outside load."""
    out = []
    for i, r in enumerate(rows):
        if r["algo"] != "ppo":
            continue
        bases = [j for j, b in enumerate(rows) if b["algo"] == "sb3-ppo" and b["delay_ms"] == r["delay_ms"]]
        if not bases:
            continue
        base = rows[min(bases, key=lambda j: (abs(j - i), j > i))]
        for fig, goal in (("env_steps_per_s", ">= 1.5"), ("rollout_env_steps_per_s", ""), ("learner_cpu_s_per_1k", "<= 0.25")):
            if r[fig] and base[fig]:
                out.append({"ratio": f"ppo / sb3-ppo {fig}", "value": round(r[fig] / base[fig], 3), "goal": goal})
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--task", default="navigation", help="task to train (default: navigation)")
    parser.add_argument("--timesteps", type=int, default=None,
                        help=f"env steps per run (default {DEFAULT_TIMESTEPS:,}; --quick {QUICK_TIMESTEPS:,})")
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_TIMESTEPS:,} env steps per run")
    parser.add_argument("--delay-ms", type=float, nargs="+", default=None, metavar="MS",
                        help="remote workers behind this added round trip; several values: one run each, "
                             "with ratios to the 0 ms run (e.g. --delay-ms 0 20)")
    parser.add_argument("--workers", type=int, default=None, help="scene workers (default: the host plan's)")
    parser.add_argument("--num-envs", type=int, default=None, help="agents (default: the host plan's)")
    parser.add_argument("--device", default=None, help="the learner's device (default: auto, as visfly-dist train)")
    parser.add_argument("--algo", nargs="+", default=[None], choices=("ppo", "sb3-ppo"),
                        help="trainer(s): ppo, sb3-ppo, or both (one run each, with their ratios); default: the task's")
    parser.add_argument("--seed", type=int, default=0, help="seed of the run")
    parser.add_argument("--overlap", action=argparse.BooleanOptionalAction, default=None,
                        help="train with --overlap / --no-overlap (next rollout collected during the update, "
                             "policy lag 1); default: as visfly-dist train (on with remote workers only)")
    parser.add_argument("--json", metavar="FILE", help="write the rows and the machine info here")


def run(args: argparse.Namespace) -> int:
    from visfly_dist.bench import report
    from visfly_dist.bench.common import load_average, machine_info

    timesteps = (QUICK_TIMESTEPS if args.quick else DEFAULT_TIMESTEPS) if args.timesteps is None else args.timesteps
    if timesteps < 1:
        raise ConfigError(f"--timesteps {timesteps} must be >= 1")
    if args.json:
        from visfly_dist.output_paths import check_output_file

        check_output_file(args.json, "--json")  # before the benchmark, not after it
    result: dict[str, Any] = {"machine": machine_info()}
    changes = {k: v for k, v in (("overlap", args.overlap), ("device", args.device), ("num_envs", args.num_envs))
               if v is not None}
    result |= bench_train(args.task, timesteps, args.delay_ms, args.workers, args.seed, algos=args.algo, changes=changes,
                          log=lambda line: print(line, flush=True))
    result["load_average_end"] = load_average()
    print(report.text_table(result["rows"]))
    if result["ratios"]:
        print(report.text_table(result["ratios"]))
    if args.json:
        report.write_json(result, args.json)
        print(f"wrote {args.json}")
    return 0
