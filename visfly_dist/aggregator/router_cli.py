"""``visfly-dist router``: a Zenoh router for a multi-machine pool (there is no ``zenohd`` here).

Workers and aggregators on other hosts connect to it as clients; runs stay apart by their run id.
Prints one line once it serves (``router ready on [...]``) and serves until SIGINT or SIGTERM.
"""

from __future__ import annotations

import argparse
import signal
import threading

from visfly_dist.aggregator.config import endpoint_problem
from visfly_dist.errors import ConfigError
from visfly_dist.protocol.session import add_zenoh_config_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                        help="endpoint to listen on (repeatable), e.g. tcp/0.0.0.0:7447")
    parser.add_argument("--no-shm", action="store_true", help="disable Zenoh shared memory")
    add_zenoh_config_argument(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from visfly_dist.protocol.session import SessionConfig, open_session

    listen = tuple(args.listen) or ("tcp/0.0.0.0:7447",)
    problems = [p for p in map(endpoint_problem, listen) if p]
    if problems:
        raise ConfigError("; ".join(problems))
    config = SessionConfig(mode="router", listen=listen, shared_memory=not args.no_shm, config_file=args.zenoh_config)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    session = open_session(config)
    try:
        print(f"router ready on {list(listen)}", flush=True)
        while not stop.wait(0.5):
            pass
    finally:
        session.close()
    return 0
