"""The ``visfly-dist`` command line: one subcommand per job, each defined in the module it runs.

Each module named below exposes ``add_arguments(parser)``, which must set ``func`` with
``parser.set_defaults(func=...)``; ``func(args) -> int`` is the exit status. Modules are imported
lazily here but keep their own top-level imports light, so ``--help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import Sequence

from visfly_dist import __version__
from visfly_dist.errors import VisflyError

SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "train": ("visfly_dist.training.train_cli", "train a flight policy (PPO, BPTT or SHAC) on a task"),
    "eval": ("visfly_dist.training.eval_cli", "evaluate a checkpoint: success rate and a video"),
    "export": ("visfly_dist.training.export_cli", "export a PPO checkpoint's actor to ONNX for a drone"),
    "worker": ("visfly_dist.scene_worker.cli", "serve scenes (render + obstacle queries) over Zenoh"),
    "router": ("visfly_dist.aggregator.router_cli", "run a Zenoh router for a multi-machine pool"),
    "launch": ("visfly_dist.aggregator.launch_cli", "keep a local pool of scene workers alive"),
    "scenes": ("visfly_dist.scene_worker.scenes_cli", "generate and preview scenes"),
    "plot": ("visfly_dist.dynamics.plot_cli", "plot controller step responses"),
    "bench": ("visfly_dist.bench.cli", "benchmarks: physics, render, step, update, train, all"),
}


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The full parser; with ``only``, import just that subcommand's module (a worker must not
    pay for, or load, torch because another subcommand imports it)."""
    parser = argparse.ArgumentParser(
        prog="visfly-dist",
        description="Distributed simulator for vision-based quadrotor reinforcement learning.",
    )
    parser.add_argument("--version", action="version", version=f"visfly-dist {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        if only is not None and name != only:
            continue
        module = importlib.import_module(module_name)
        module.add_arguments(sub.add_parser(name, help=help_text, description=help_text))
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(only=argv[0] if argv and argv[0] in SUBCOMMANDS else None)
    args = parser.parse_args(argv)
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 2 if args.command is None else 0
    try:
        return int(func(args) or 0)
    except VisflyError as exc:
        print(f"visfly-dist {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
