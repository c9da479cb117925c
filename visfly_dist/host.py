"""What this host gives a process: usable cores and memory (standard library only; any module may import it).

``os.cpu_count()`` counts the machine's cores; a process may be confined to fewer by its CPU
affinity (``taskset``, Slurm, Docker's ``--cpuset-cpus``) and throttled by a cgroup CPU quota
(Docker's ``--cpus``, Kubernetes limits). Sizing threads from the machine's count oversubscribes
the cores this process really has; these functions read what applies to it.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

CGROUP_ROOT = Path("/sys/fs/cgroup")


def cgroup_cpu_limit(root: Path = CGROUP_ROOT, proc_self: Path = Path("/proc/self/cgroup")) -> float | None:
    """The CPU quota of this process's cgroup in cores (``None``: no quota), cgroup v2 or v1."""
    for path in _own_cgroup_dirs(root, proc_self):
        v2 = path / "cpu.max"
        if v2.is_file():
            quota, _, period = v2.read_text().strip().partition(" ")
            if quota != "max" and period:
                return int(quota) / int(period)
        v1_quota, v1_period = path / "cpu.cfs_quota_us", path / "cpu.cfs_period_us"
        if v1_quota.is_file() and v1_period.is_file():
            quota_us = int(v1_quota.read_text())
            if quota_us > 0:
                return quota_us / int(v1_period.read_text())
    return None


def _own_cgroup_dirs(root: Path, proc_self: Path) -> list[Path]:
    """The cgroup folders of this process, innermost first (v2 unified and v1 ``cpu`` hierarchies)."""
    out: list[Path] = []
    try:
        lines = proc_self.read_text().splitlines()
    except OSError:
        return [root]
    for line in lines:
        _, controllers, rel = line.split(":", 2)
        rel = rel.lstrip("/")
        bases = [root] if controllers == "" else [root / "cpu", root / "cpu,cpuacct"] if "cpu" in controllers.split(",") else []
        for base in bases:
            here = base / rel
            while True:
                out.append(here)
                if here == base:
                    break
                here = here.parent
    return out or [root]


def usable_cores() -> int:
    """Cores this process may use: its CPU affinity, capped by its cgroup quota (rounded up), at least 1."""
    cores = len(os.sched_getaffinity(0))
    try:
        quota = cgroup_cpu_limit()
    except (OSError, ValueError):
        quota = None
    if quota is not None:
        cores = min(cores, max(1, math.ceil(quota)))
    return max(1, cores)


def available_memory_bytes() -> int:
    """Memory this process may still take: ``MemAvailable``, capped by its cgroup's limit minus usage."""
    available = 0
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                available = int(line.split()[1]) * 1024
    except OSError:
        available = 0
    limit_file, usage_file = CGROUP_ROOT / "memory.max", CGROUP_ROOT / "memory.current"
    try:
        limit = limit_file.read_text().strip()
        if limit != "max":
            available = min(available or 1 << 62, int(limit) - int(usage_file.read_text()))
    except (OSError, ValueError):
        pass
    return max(0, available)
