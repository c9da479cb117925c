"""``visfly-dist eval TASK --checkpoint PATH``: deterministic and sampled success side by side.

Example::

    visfly-dist eval hover --checkpoint runs/hover-1/final.zip --episodes 100 --video hover.gif --json hover.json

The env is built with the settings of the training run (its ``config.json`` next to the checkpoint
or one folder up), then ``--seed``, ``--scene-root`` and ``--set`` changes; the observation
normalisation saved with the checkpoint (``*.norm.npz``) is applied. Both modes (``--mode both``,
the default) run from the same seed, so they start from the same spawns: ``deterministic`` takes
the policy's mean action, ``sampled`` draws actions as in training. Each line gives the success
rate with its Wilson 95 % interval and how the episodes ended; in team tasks (``gap_crossing``)
an episode is a team's, a success only when every member succeeds. The default seed (12345) differs
from training's, so generated scenes (seeded from the env seed) and spawns are ones training never
saw; an equal seed is refused unless ``--allow-training-seed``. A BPTT/SHAC checkpoint (``.npz``)
is a deterministic actor: it is evaluated in the deterministic mode only. A recurrent checkpoint
(``train --recurrent``, sb3-contrib RecurrentPPO, recognised from the zip) carries each agent's LSTM
state from step to step, zeroed where its episode starts. Scene files are not drawn from the
seed: hold some out of training and pass them with ``--scene-root DIR --set scenes='["held_out/*.glb"]'``.

``--video`` films agent 0 in the first mode: its first episode, or with ``--video-success`` its
first successful one (its camera image beside a chase camera, at the env's rate; see
:mod:`visfly_dist.training.video`). ``--json`` writes, per mode, the figures, the seed, the scene
sources and every episode's end cause (``success``, ``collision``, ``out_of_bounds``, ``lost``,
``failure``, ``time_limit``, ``swapped``; see :mod:`visfly_dist.tasks.outcomes`).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
from pathlib import Path
from typing import Any

from visfly_dist.protocol.session import add_zenoh_config_argument
from visfly_dist.training.config import parse_override
from visfly_dist.training.train_cli import add_scene_root, scene_roots, with_zenoh_config

MODES = {"both": (True, False), "deterministic": (True,), "sampled": (False,)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("task", help="task name: navigation, hover, landing, gap_crossing, racing, tracking, navigation_moving")
    parser.add_argument("--checkpoint", required=True,
                        help="model written by 'visfly-dist train': .zip (PPO) or .npz (BPTT/SHAC actor, deterministic only)")
    parser.add_argument("--episodes", type=int, default=100, help="episodes per mode (default 100)")
    parser.add_argument("--mode", choices=tuple(MODES), default="both",
                        help="deterministic (mean action), sampled (as in training), or both side by side (default)")
    parser.add_argument("--num-envs", type=int, help="parallel agents (default: the training run's)")
    parser.add_argument("--video", metavar="FILE.gif", help="film agent 0 in the first mode")
    parser.add_argument("--video-success", action="store_true",
                        help="film agent 0's first successful episode (with none, its first episode, and the summary says so)")
    parser.add_argument("--json", metavar="FILE", help="write the figures, seed, scenes and every episode as JSON")
    parser.add_argument("--seed", type=int, default=12345, help="env seed (default 12345, unlike training's)")
    parser.add_argument("--allow-training-seed", action="store_true", help="evaluate with the training run's own seed")
    parser.add_argument("--workers", type=int, help="local scene workers to spawn")
    parser.add_argument("--connect", action="append", default=[], metavar="EP", help="Zenoh endpoint to join (repeatable)")
    parser.add_argument("--run-id", help="key namespace (default: random)")
    parser.add_argument("--backend", choices=("auto", "egl", "raycast"), help="renderer of local workers")
    parser.add_argument("--device", default="auto", help="torch device of the policy (default auto: cuda when torch sees a GPU)")
    add_scene_root(parser)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="env setting passed to make_env (repeatable)")
    add_zenoh_config_argument(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from visfly_dist.errors import ConfigError
    from visfly_dist.output_paths import check_output_file
    from visfly_dist.training.evaluation import find_run_config, missing_normalization
    from visfly_dist.training.host_plan import check_device

    if args.episodes < 1:
        raise ConfigError(f"--episodes {args.episodes} must be >= 1")
    if args.num_envs is not None and args.num_envs < 1:
        raise ConfigError(f"--num-envs {args.num_envs} must be >= 1 (leave it out for the training run's)")
    device = check_device(args.device)
    checkpoint = Path(args.checkpoint)
    if not checkpoint.is_file() or checkpoint.suffix not in (".zip", ".npz"):
        raise ConfigError(f"--checkpoint {str(checkpoint)!r} is not a checkpoint; pass a .zip (PPO) or .npz (BPTT/SHAC) "
                          "written by 'visfly-dist train'")
    if args.video is not None:  # checked before the evaluation that fills them
        check_output_file(args.video, "--video", (".gif",))
    if args.json is not None:
        check_output_file(args.json, "--json")
    differentiable = checkpoint.suffix == ".npz"
    if differentiable and args.mode == "sampled":
        raise ConfigError(f"--mode sampled: {checkpoint} is a BPTT/SHAC actor, which is deterministic; use --mode deterministic")
    modes = (True,) if differentiable else MODES[args.mode]
    run_cfg = find_run_config(checkpoint)
    train_seed = run_cfg.seed if run_cfg is not None else None
    if train_seed == args.seed and not args.allow_training_seed:
        raise ConfigError(f"--seed {args.seed} is the training run's seed: its scenes and spawns were seen in training; "
                          "pick another seed (or pass --allow-training-seed)")
    warning = None if differentiable else missing_normalization(checkpoint, run_cfg)
    if warning is not None:
        print(f"visfly-dist eval: warning: {warning}", file=sys.stderr, flush=True)
    overrides = with_zenoh_config(dict(parse_override(item) for item in args.set), args.zenoh_config)
    pool = dict(workers=args.workers, connect=tuple(args.connect) or None, run_id=args.run_id, backend=args.backend,
                scene_roots=scene_roots(args) or None)
    # SIGTERM (kill, timeout, Slurm) unwinds as Ctrl-C does: the workers stop and the shared memory goes
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        return _evaluate(args, checkpoint, differentiable, modes, run_cfg, train_seed, overrides, pool, device)
    finally:
        signal.signal(signal.SIGTERM, previous)


def _terminate(signum: int, frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def _evaluate(args: argparse.Namespace, checkpoint: Path, differentiable: bool, modes: tuple[bool, ...],
              run_cfg: Any, train_seed: int | None, overrides: dict[str, Any], pool: dict[str, Any], device: str) -> int:
    """Build the env, evaluate each mode, film, report (``run``'s second half)."""
    from visfly_dist.training.bptt import load_actor
    from visfly_dist.training.evaluation import Policy, build_eval_env, evaluate, load_policy
    from visfly_dist.training.video import VideoRecorder

    env = build_eval_env(args.task, args.num_envs, args.seed, run_cfg, overrides, pool)
    recorder, results = None, []
    try:
        model: Policy
        if differentiable:
            model = load_actor(checkpoint, env.unwrapped, run_cfg.backbone if run_cfg is not None else "visfly-cnn")
        else:
            model, env = load_policy(checkpoint, env, device)
        recorder = VideoRecorder(env.unwrapped) if args.video else None
        for k, deterministic in enumerate(modes):
            results.append(evaluate(model, env, args.episodes, deterministic=deterministic, seed=args.seed,
                                    recorder=recorder if k == 0 else None, film_success=args.video_success))
        if recorder is not None:
            recorder.save(args.video)
    finally:
        if recorder is not None:
            recorder.close()
        env.close()
    print(f"{args.task}: {args.checkpoint}, seed {args.seed} (training seed {train_seed})")
    for stats in results:
        print(stats.line())
    if recorder is not None:
        first = results[0]
        print(f"video {args.video}: {first.video_frames} frames, {'a success' if first.video_success else 'no success'}")
    if args.json:
        report = dict(task=args.task, checkpoint=str(checkpoint), seed=args.seed, training_seed=train_seed,
                      episodes_per_mode=args.episodes, results={s.mode: s.to_dict() for s in results})
        Path(args.json).write_text(json.dumps(report, indent=2) + "\n")
    return 0
