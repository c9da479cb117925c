"""``visfly-dist bench``: one sub-command per benchmark, each in its own module.

Each module exposes ``add_arguments(parser)`` and ``run(args) -> int``. Every benchmark also takes
``--zenoh-config FILE``, handed to all the sessions it opens (its own and its workers') as
``$ZENOH_CONFIG``.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import os

from visfly_dist.errors import ConfigError
from visfly_dist.protocol.session import ZENOH_CONFIG_ENV, add_zenoh_config_argument, load_config_file, resolve_config_file

BENCHMARKS: dict[str, tuple[str, str]] = {
    "physics": ("visfly_dist.bench.physics", "batched dynamics: agent-steps/s, eager and compiled"),
    "render": ("visfly_dist.bench.render", "renderers and obstacle queries: frames/s in-process and via a worker"),
    "step": ("visfly_dist.bench.step", "full VecEnv.step env-steps/s with a per-stage breakdown"),
    "update": ("visfly_dist.bench.update", "one PPO update of the default policy alone: CPU and wall seconds"),
    "train": ("visfly_dist.bench.train", "the default training loop: whole-loop and rollout env-steps/s, busy shares"),
    "all": ("visfly_dist.bench.suite", "everything, with the pybullet peer, plots and BENCHMARKS.md"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="bench", metavar="BENCHMARK", required=True)
    for name, (module_name, help_text) in BENCHMARKS.items():
        module = importlib.import_module(module_name)
        p = sub.add_parser(name, help=help_text, description=help_text)
        module.add_arguments(p)
        add_zenoh_config_argument(p)
        p.set_defaults(func=functools.partial(_with_zenoh_config, module.run))


def _with_zenoh_config(run, args: argparse.Namespace) -> int:
    """Run a benchmark with ``--zenoh-config`` exported as ``$ZENOH_CONFIG`` (checked first)."""
    if args.zenoh_config is not None:
        path = resolve_config_file(args.zenoh_config)
        if path is None:  # an empty --zenoh-config and no $ZENOH_CONFIG
            raise ConfigError(f"--zenoh-config {args.zenoh_config!r} names no file")
        load_config_file(path)
        os.environ[ZENOH_CONFIG_ENV] = path
    return run(args)
