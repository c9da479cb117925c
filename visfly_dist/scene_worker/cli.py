"""``visfly-dist worker``: serve scenes to one run over Zenoh until SIGTERM/SIGINT or the parent dies.

Prints one line to stdout once it serves (launchers and tests wait for it)::

    worker W ready on run R: backend B, tracer T[, GL device 'D'], listening on [...] / connected to [...]

``T`` is the raycast backend's tracer: ``native`` (packets) or ``embreex`` (the fallback); ``D`` the
``GL_RENDERER`` of the egl backend's EGL device (``egl`` and ``auto`` workers that have one; the egl
renderer is the batch renderer of :mod:`visfly_dist.scene_worker.render_egl_batch`).

With ``--connect`` alone the worker is a Zenoh client of those endpoints (a router or a listening
aggregator); with ``--listen`` it is a peer listening there (others connect to it).
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import signal
import socket
import sys

from visfly_dist.errors import ConfigError
from visfly_dist.protocol.session import add_zenoh_config_argument
from visfly_dist.scene_worker.limits import WorkerLimits

ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws)/(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.\-]+):(?P<port>\d{1,5})([?#].*)?$")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--run-id", required=True, help="run namespace shared with the aggregator")
    parser.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                        help="endpoint to connect to, e.g. tcp/10.0.0.5:7447 (repeatable)")
    parser.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                        help="endpoint to listen on, e.g. tcp/127.0.0.1:7450 (repeatable)")
    parser.add_argument("--mode", choices=("peer", "client"), default=None,
                        help="Zenoh mode; default client with --connect alone, peer with --listen")
    parser.add_argument("--scene-root", action="append", default=[], metavar="DIR",
                        help="folder scene files may be loaded from (repeatable; default: current dir)")
    parser.add_argument("--backend", choices=("auto", "egl", "raycast"), default="auto",
                        help="renderer: egl (OpenGL batch renderer over EGL), raycast (ray tracer), auto (per scene's cameras)")
    parser.add_argument("--threads", type=int, default=None,
                        help="raycast tracing threads, and the loads run at once before the first step, their "
                             "generation in N-1 child processes (default: the CPUs this process may use, at most 8)")
    parser.add_argument("--worker-id", default=None, help="id in the run (default: <host>-<pid>)")
    parser.add_argument("--no-shm", action="store_true",
                        help="disable shared memory: Zenoh's, and image segments (images travel in the reply)")
    parser.add_argument("--lease-ms", type=int, default=2000,
                        help="link lease: a hung worker is declared dead after about this long")
    parser.add_argument("--parent-pid", type=int, default=None, metavar="PID",
                        help="exit when this process is gone (local pools)")
    parser.add_argument("--channel-fd", type=int, default=None, metavar="FD",
                        help="an inherited socket on which the trainer that started this worker sends requests "
                             "besides Zenoh (set by local pools; see visfly_dist.protocol.local_channel)")
    limits = parser.add_argument_group("bounds (a request beyond them gets an error reply)")
    limits.add_argument("--max-scenes", type=int, default=WorkerLimits.max_scenes, metavar="N",
                        help="scenes loaded or loading at once (default %(default)s)")
    limits.add_argument("--max-key-chars", type=int, default=WorkerLimits.max_key_chars, metavar="N",
                        help="length of a scene key (default %(default)s, at most 256)")
    limits.add_argument("--max-pixels", type=int, default=WorkerLimits.max_pixels, metavar="N",
                        help="agents x cameras x pixels one step may render (default %(default)s)")
    limits.add_argument("--max-memory-mb", type=int, default=None, metavar="MB",
                        help="resident memory of this worker beyond which scene loads are refused (overloaded); "
                             "default: half the host's physical memory")
    add_zenoh_config_argument(parser)
    parser.set_defaults(func=run)


def check_endpoint(endpoint: str) -> str:
    """Return ``endpoint`` if it looks like ``PROTO/HOST:PORT``; ConfigError otherwise."""
    m = ENDPOINT.match(endpoint)
    if not m or int(m.group("port")) > 65535:
        raise ConfigError(f"endpoint {endpoint!r} must look like tcp/HOST:PORT (tcp, udp, tls, quic, ws; "
                          "port 0-65535), e.g. tcp/127.0.0.1:7447")
    return endpoint


def session_config(args: argparse.Namespace):
    """The SessionConfig the arguments ask for; ConfigError on contradictions."""
    from visfly_dist.protocol.session import SessionConfig

    connect = tuple(check_endpoint(e) for e in args.connect)
    listen = tuple(check_endpoint(e) for e in args.listen)
    if not connect and not listen:
        raise ConfigError("give --connect ENDPOINT (join a router or aggregator) or --listen ENDPOINT (be reached)")
    mode = args.mode or ("peer" if listen else "client")
    if mode == "client" and listen:
        raise ConfigError(f"--listen {list(listen)} needs --mode peer: a Zenoh client does not listen")
    return SessionConfig(mode=mode, connect=connect, listen=listen, shared_memory=not args.no_shm,
                         lease_ms=args.lease_ms, config_file=args.zenoh_config)


def parent_gone(parent_pid: int, original_ppid: int) -> bool:
    """Whether ``parent_pid`` has exited (or, if it was our parent, we were re-parented)."""
    if parent_pid == original_ppid and os.getppid() != original_ppid:
        return True
    try:
        os.kill(parent_pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # alive, owned by someone else
        return False
    return False


def inherited_socket(fd: int) -> socket.socket:
    """The Unix stream socket behind inherited descriptor ``fd``; ConfigError if it is not one."""
    try:
        sock = socket.socket(fileno=fd)
    except OSError as exc:
        raise ConfigError(f"--channel-fd {fd} is not an open socket: {exc}") from None
    if sock.family != socket.AF_UNIX or sock.type != socket.SOCK_STREAM:
        sock.detach()
        raise ConfigError(f"--channel-fd {fd} must be a Unix stream socket (local pools pass one)")
    return sock


def run(args: argparse.Namespace) -> int:
    roots = args.scene_root or [os.getcwd()]
    missing = [r for r in roots if not os.path.isdir(r)]
    if missing:
        raise ConfigError(f"--scene-root {missing} are not existing directories")
    config = session_config(args)
    memory = {} if args.max_memory_mb is None else {"max_memory_bytes": args.max_memory_mb * 1024 * 1024}
    limits = WorkerLimits(max_scenes=args.max_scenes, max_key_chars=args.max_key_chars, max_pixels=args.max_pixels,
                          **memory)
    if args.threads is not None and args.threads < 1:
        raise ConfigError(f"--threads {args.threads} must be >= 1")
    if args.parent_pid is not None and args.parent_pid <= 0:
        raise ConfigError(f"--parent-pid {args.parent_pid} must be a positive process id")
    channel = None if args.channel_fd is None else inherited_socket(args.channel_fd)
    if "torch" in sys.modules:  # never import it here; only tame it if something else did
        sys.modules["torch"].set_num_threads(1)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s worker %(process)d %(levelname)s %(message)s")

    from visfly_dist.protocol.shm import release_segments
    from visfly_dist.scene_worker.service import SceneWorker

    worker = SceneWorker(args.run_id, config, roots, backend=args.backend, worker_id=args.worker_id, limits=limits,
                         threads=args.threads, channel=channel)
    original_ppid = os.getppid()
    should_stop = None
    if args.parent_pid is not None:
        should_stop = lambda: parent_gone(args.parent_pid, original_ppid)  # noqa: E731
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: worker.stop())
    try:
        worker.start()
        where = f"listening on {list(config.listen)}" if config.listen else f"connected to {list(config.connect)}"
        gl = f"GL device {worker.gl_device!r}, " if worker.gl_device else ""
        print(f"worker {worker.worker_id} ready on run {args.run_id}: backend {args.backend}, "
              f"tracer {worker.tracer}, {gl}{where}", flush=True)
        worker.serve(should_stop=should_stop)
    finally:
        worker.close()
    release_segments()
    return 0
