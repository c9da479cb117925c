"""``visfly-dist launch``: keep a local pool of scene workers alive for a run.

Starts ``--workers N`` workers connected to ``--connect``, restarts any that exits (same worker id,
after a backoff that doubles on each quick crash, logging every restart), and stops them all on
SIGINT or SIGTERM. The aggregator notices a restart by the worker's new liveliness token and
reloads its scenes there.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import socket
import sys
import tempfile
import threading
import time

from visfly_dist.aggregator.config import BACKENDS, endpoint_problem
from visfly_dist.aggregator.launcher import LocalWorker, WorkerLaunchSpec, stop_workers
from visfly_dist.errors import ConfigError
from visfly_dist.host import usable_cores
from visfly_dist.protocol.keys import check_chunk
from visfly_dist.protocol.session import add_zenoh_config_argument, lease_problem, load_config_file, resolve_config_file

log = logging.getLogger("visfly_dist.launch")

BACKOFF_FIRST_S = 0.5
BACKOFF_MAX_S = 30.0
HEALTHY_AFTER_S = 60.0  # a worker that ran this long before exiting restarts without backoff


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--workers", type=int, required=True, help="number of workers to keep alive")
    parser.add_argument("--run-id", required=True, help="run namespace shared with the aggregator")
    parser.add_argument("--connect", action="append", required=True, metavar="ENDPOINT",
                        help="router or aggregator endpoint the workers connect to (repeatable)")
    parser.add_argument("--scene-root", action="append", default=[], metavar="DIR",
                        help="folder scene files may be loaded from (repeatable)")
    parser.add_argument("--threads", type=int, default=None,
                        help="tracing threads of each worker (default: this host's usable cores divided among the workers)")
    parser.add_argument("--backend", choices=BACKENDS, default="auto", help="renderer of the workers")
    parser.add_argument("--worker-prefix", default=None,
                        help="worker ids are PREFIX-0 .. PREFIX-(N-1) (default: the host name)")
    parser.add_argument("--no-shm", action="store_true", help="disable Zenoh shared memory")
    parser.add_argument("--lease-ms", type=int, default=2000, help="worker link lease (hang detection)")
    parser.add_argument("--log-dir", default=None, help="where worker logs go (default: a temporary folder)")
    add_zenoh_config_argument(parser)
    parser.set_defaults(func=run)


def _default_prefix() -> str:
    return "".join(c if c.isalnum() or c in "_.-" else "-" for c in socket.gethostname()) or "host"


def _check(args: argparse.Namespace) -> None:
    problems = [p for p in map(endpoint_problem, args.connect) if p]
    if args.threads is not None and args.threads < 1:
        problems.append(f"--threads {args.threads} must be >= 1")
    if args.workers < 1:
        problems.append(f"--workers {args.workers} must be >= 1")
    lease = lease_problem(args.lease_ms)
    if lease:  # the workers would refuse it and be restarted for ever
        problems.append(f"--lease-ms: {lease}")
    problems += [f"--scene-root {r!r} is not a directory" for r in args.scene_root if not os.path.isdir(r)]
    for value, what in ((args.run_id, "--run-id"), (args.worker_prefix or "x", "--worker-prefix")):
        try:
            check_chunk(value, what)
        except ConfigError as exc:
            problems.append(str(exc))
    zenoh_config = resolve_config_file(args.zenoh_config)
    if zenoh_config is not None:
        try:
            load_config_file(zenoh_config)
        except ConfigError as exc:
            problems.append(str(exc))
    if problems:
        raise ConfigError("; ".join(problems))


def run(args: argparse.Namespace) -> int:
    _check(args)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(asctime)s launch %(levelname)s %(message)s")
    spec = WorkerLaunchSpec(run_id=args.run_id, connect=tuple(args.connect), scene_roots=tuple(args.scene_root),
                            backend=args.backend, shared_memory=not args.no_shm, lease_ms=args.lease_ms,
                            parent_pid=os.getpid(), zenoh_config=resolve_config_file(args.zenoh_config),
                            threads=args.threads or max(1, usable_cores() // args.workers))
    log_dir = args.log_dir or tempfile.mkdtemp(prefix=f"visfly-launch-{args.run_id}-")
    os.makedirs(log_dir, exist_ok=True)
    prefix = args.worker_prefix or _default_prefix()
    ids = [f"{prefix}-{i}" for i in range(args.workers)]

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())

    def start(wid: str) -> LocalWorker:
        return LocalWorker(wid, spec.argv(wid), os.path.join(log_dir, f"{wid}.log"))

    workers = {wid: start(wid) for wid in ids}
    crashes = {wid: 0 for wid in ids}
    restart_at: dict[str, float] = {}
    print(f"launch ready: {args.workers} workers {ids} on run {args.run_id}, logs in {log_dir}", flush=True)
    try:
        while not stop.wait(0.2):
            now = time.monotonic()
            for wid in ids:
                worker = workers[wid]
                if wid in restart_at:
                    if now >= restart_at[wid]:
                        del restart_at[wid]
                        workers[wid] = start(wid)
                        log.info("restarted worker %s (pid %d)", wid, workers[wid].pid)
                    continue
                if worker.running():
                    continue
                lived = now - worker.started_at
                crashes[wid] = 0 if lived >= HEALTHY_AFTER_S else crashes[wid] + 1
                delay = 0.0 if crashes[wid] == 0 else min(BACKOFF_MAX_S, BACKOFF_FIRST_S * 2 ** (crashes[wid] - 1))
                restart_at[wid] = now + delay
                log.warning("worker %s exited with %s after %.1f s; restarting in %.1f s; last output: %s",
                            wid, worker.process.returncode, lived, delay, worker.log_tail(300))
    finally:
        stop_workers(workers.values())
        print("launch stopped", flush=True)
    return 0
