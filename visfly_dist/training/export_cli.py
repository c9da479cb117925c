"""``visfly-dist export TASK --checkpoint RUN/final.zip --out policy.onnx``: the actor as ONNX, for a drone.

Example::

    visfly-dist export navigation --checkpoint runs/navigation-1/final.zip --out navigation.onnx
    python deploy/onnx_runner.py navigation.onnx --describe

The file takes the raw observations (depth in metres, state, target... as the env gives them; the
run's observation normalisation, ``final.norm.npz``, is inside) and gives ``action``: the policy's
deterministic (mean) action clipped to [-1, 1], the command of the task's controller. Its metadata
says what each input holds, the control rate and the mapping of ``action`` to the physical command
(see :mod:`visfly_dist.training.export` and docs/DEPLOY.md). The run's ``config.json`` (next to the
checkpoint or one folder up) supplies the env settings; ``--set`` changes them as in training.
A ``train --recurrent`` checkpoint (RecurrentPPO) is exported with its actor LSTM's state as
``hidden_in`` / ``hidden_out`` ``(B, 2, layers, units)``: h then c; feed ``hidden_out`` back each step and
zeros at an episode's start (the runner does: ``OnnxPolicy.act`` carries it, ``reset`` zeroes it).
"""

from __future__ import annotations

import argparse
import sys

from visfly_dist.training.config import parse_override


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("task", help="the task the policy was trained on: navigation, hover, landing, gap_crossing, tracking, ...")
    parser.add_argument("--checkpoint", required=True, help="PPO model written by 'visfly-dist train' (.zip; its .norm.npz beside it)")
    parser.add_argument("--out", required=True, metavar="FILE.onnx", help="where to write the ONNX file")
    parser.add_argument("--opset", type=int, default=17, help="ONNX opset (default 17)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="env setting of the run (repeatable), when it has no config.json or differs from it")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from visfly_dist.tasks.registry import check_setting_names
    from visfly_dist.training.config import TrainConfig
    from visfly_dist.training.evaluation import find_run_config, missing_normalization
    from visfly_dist.training.export import check_exportable, describe, export_checkpoint
    from visfly_dist.training.ppo import env_kwargs

    settings = None
    check_exportable(Path(args.checkpoint))
    run_cfg = find_run_config(Path(args.checkpoint))
    warning = missing_normalization(Path(args.checkpoint), run_cfg)  # raises where the run normalised
    if warning is not None:
        print(f"visfly-dist export: warning: {warning}", file=sys.stderr, flush=True)
    if args.set:
        given = dict(parse_override(item) for item in args.set)
        check_setting_names(args.task, given)  # they only fill the metadata: a typo would leave a wrong rate there
        cfg = run_cfg if run_cfg is not None and run_cfg.task == args.task else TrainConfig(task=args.task)
        cfg.overrides = {**cfg.overrides, **given}
        settings = env_kwargs(cfg.resolved())
    info = export_checkpoint(args.task, args.checkpoint, args.out, settings, opset=args.opset)
    print(describe(info))
    return 0
