"""Helpers shared by the benchmarks: timing a callable, describing the machine a run was on, clear
drone poses in a scene, and the stages a step is split into.

Figures from these machines are noisy (they are shared), so a timing keeps every repetition and
reports the median; the load average before and after a run says how busy the machine was.
"""

from __future__ import annotations

import datetime as _dt
import os
import platform
import shlex
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from visfly_dist.errors import ConfigError

REPO_ROOT = Path(__file__).resolve().parents[2]
STAGES = ("physics", "transport", "render", "queries", "other")
"""The stages a measured env step is split into (the step bench's rows and its report)."""
DRONE_RADIUS = 0.1
CLEARANCE = 0.3


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


@dataclass(frozen=True)
class Timing:
    """Wall-clock seconds of each repetition of one piece of work."""

    seconds: tuple[float, ...]

    @property
    def median(self) -> float:
        return statistics.median(self.seconds)

    def rate(self, work: float) -> float:
        """``work`` units done per second, from the median repetition."""
        return work / self.median if self.median > 0 else float("inf")


def time_it(fn: Callable[[], Any], *, reps: int = 3, warmup: int = 1) -> Timing:
    """Call ``fn`` ``warmup`` times untimed, then ``reps`` times timed.

    Args:
        fn: the work, with no arguments (a closure).
        reps: timed repetitions, >= 1.
        warmup: untimed calls first (caches, compilation, first-touch allocations).
    """
    assert reps >= 1 and warmup >= 0
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return Timing(tuple(out))


class Stopwatch:
    """Elapsed wall time since construction, for progress lines."""

    def __init__(self) -> None:
        self._t0 = time.perf_counter()

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self._t0


def cpu_model() -> str:
    """The CPU's model name (from ``/proc/cpuinfo`` on Linux), or the platform's guess."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def git_commit(repo: Path = REPO_ROOT) -> str | None:
    """The checked-out commit (with ``-dirty`` when the tree has changes), or None outside git."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True, timeout=10)
        if head.returncode != 0:
            return None
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=repo,
                               capture_output=True, text=True, timeout=10)
        return head.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return None


def _version(module: str) -> str | None:
    try:
        mod = __import__(module)
    except Exception:  # an optional dependency that is missing or broken is reported as None
        return None
    return str(getattr(mod, "__version__", "unknown"))


def load_average() -> list[float] | None:
    """1, 5 and 15 minute load averages (None where the OS has none)."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def machine_info(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """What a benchmark figure needs beside it to be read: machine, versions, date, commit, command."""
    from visfly_dist import __version__

    argv = list(sys.argv if argv is None else argv)
    if argv and argv[0].endswith(("cli.py", "__main__.py", "visfly-dist")):
        argv = ["visfly-dist"] + argv[1:]
    return {
        "cpu_model": cpu_model(),
        "cores": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": _version("torch"),
        "numpy": _version("numpy"),
        "embreex": _pip_version("embreex"),
        "pybullet": _pip_version("pybullet"),
        "visfly_dist": __version__,
        "git_commit": git_commit(),
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "command": shlex.join(argv),
        "load_average_start": load_average(),
    }


def _pip_version(dist: str) -> str | None:
    from importlib import metadata

    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None
