"""``visfly-dist eval TASK --checkpoint PATH``: success rate, returns, collisions, and a video.

Example::

    visfly-dist eval navigation --checkpoint runs/navigation-20261121-2020/final.zip --episodes 50 \\
        --video nav.gif --deterministic

The env is built with the settings of the training run (its ``config.json`` next to the checkpoint
or one folder up), then ``--set`` changes; the observation normalisation saved with the checkpoint
(``*.norm.npz``) is applied. ``--video`` films agent 0's first episode: its camera image beside a
chase camera (see :mod:`visfly_dist.training.video`). ``--json`` writes the figures as JSON.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from visfly_dist.protocol.session import add_zenoh_config_argument
from visfly_dist.training.config import parse_override
from visfly_dist.training.train_cli import with_zenoh_config


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("task", help="task name: navigation, hover, landing, gap_crossing, racing")
    parser.add_argument("--checkpoint", required=True, help="model .zip written by 'visfly-dist train'")
    parser.add_argument("--episodes", type=int, default=20, help="episodes to evaluate (default 20)")
    parser.add_argument("--num-envs", type=int, help="parallel agents (default: the training run's)")
    parser.add_argument("--deterministic", action="store_true",
                        help="take the policy's mean action (default: sample, as in training; briefly trained "
                             "policies often do much worse on their mean action)")
    parser.add_argument("--video", metavar="FILE.gif", help="film agent 0's first episode")
    parser.add_argument("--json", metavar="FILE", help="write the figures as JSON")
    parser.add_argument("--seed", type=int, default=12345, help="env seed (default 12345, unlike training's)")
    parser.add_argument("--workers", type=int, help="local scene workers to spawn")
    parser.add_argument("--connect", action="append", default=[], metavar="EP", help="Zenoh endpoint to join (repeatable)")
    parser.add_argument("--run-id", help="key namespace (default: random)")
    parser.add_argument("--backend", choices=("auto", "egl", "raycast"), help="renderer of local workers")
    parser.add_argument("--device", default="cpu", help="torch device of the policy (default cpu)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="env setting passed to make_env (repeatable)")
    add_zenoh_config_argument(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from visfly_dist.errors import ConfigError
    from visfly_dist.training.evaluation import build_eval_env, evaluate, find_run_config, load_policy
    from visfly_dist.training.video import VideoRecorder

    if args.episodes < 1:
        raise ConfigError(f"--episodes {args.episodes} must be >= 1")
    checkpoint = Path(args.checkpoint)
    if not checkpoint.is_file():
        raise ConfigError(f"--checkpoint {str(checkpoint)!r} does not exist; pass a .zip written by 'visfly-dist train'")
    overrides = with_zenoh_config(dict(parse_override(item) for item in args.set), args.zenoh_config)
    pool = dict(workers=args.workers, connect=tuple(args.connect) or None, run_id=args.run_id, backend=args.backend)
    env = build_eval_env(args.task, args.num_envs, args.seed, find_run_config(checkpoint), overrides, pool)
    recorder = None
    try:
        model, env = load_policy(checkpoint, env, args.device)
        recorder = VideoRecorder(env.unwrapped) if args.video else None
        stats = evaluate(model, env, args.episodes, deterministic=args.deterministic, recorder=recorder)
        if recorder is not None:
            recorder.save(args.video)
    finally:
        if recorder is not None:
            recorder.close()
        env.close()
    print(
        f"{args.task}: {stats.episodes} episodes  success rate {stats.success_rate:.2f}  "
        f"mean return {stats.mean_return:.2f}  mean length {stats.mean_length:.1f}  "
        f"collisions {stats.collisions}  out of bounds {stats.out_of_bounds}"
        + (f"  video {args.video} ({stats.video_frames} frames)" if args.video else "")
    )
    if args.json:
        Path(args.json).write_text(json.dumps(stats.to_dict(), indent=2) + "\n")
    return 0
