"""``visfly-dist train TASK``: PPO (or ``--algo bptt|shac``) on a task, with logs, checkpoints and a success curve.

Example::

    visfly-dist train navigation                      # task defaults, local workers
    visfly-dist train hover --timesteps 50000 --num-envs 8 --set max_episode_steps=128
    visfly-dist train navigation --connect tcp/10.0.0.5:7447 --run-id exp1 --workers 0
    visfly-dist train hover --algo bptt --horizon 32 --lr 1e-3   # through the dynamics (or shac)
    visfly-dist train navigation --scene-root scenes --set scenes='["my_garage/*.glb"]'

Defaults depend on the task (``visfly_dist.training.config.TASK_DEFAULTS``); the resolved config is
printed at the start and saved in the run folder. See :mod:`visfly_dist.training.ppo` (and
:mod:`visfly_dist.training.bptt`) for what a run writes, and :mod:`visfly_dist.training.extractors`
for training with your own algorithm.
"""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

from visfly_dist.errors import ConfigError
from visfly_dist.protocol.session import add_zenoh_config_argument, load_config_file, resolve_config_file
from visfly_dist.training import stop
from visfly_dist.training.config import ALGOS, BACKBONES, TrainConfig, parse_override


def with_zenoh_config(overrides: dict, zenoh_config: str | None) -> dict:
    """``overrides`` with ``--zenoh-config`` (absolute, checked) in its ``pool`` map, when given."""
    if zenoh_config is None:
        return overrides
    path = resolve_config_file(zenoh_config)
    if path is None:  # an empty --zenoh-config and no $ZENOH_CONFIG
        raise ConfigError(f"--zenoh-config {zenoh_config!r} names no file")
    load_config_file(path)
    pool = overrides.get("pool")
    pool = dict(pool) if isinstance(pool, dict) else {}
    return {**overrides, "pool": {**pool, "zenoh_config": path}}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("task", help="task name: navigation, hover, landing, gap_crossing, racing, tracking, navigation_moving")
    parser.add_argument("--timesteps", type=int, help="total env steps (default: per task)")
    parser.add_argument("--num-envs", type=int, help="parallel agents (default: the task's, scaled by the host plan)")
    parser.add_argument("--workers", type=int, help="local scene workers to spawn (default: the host plan's)")
    parser.add_argument("--connect", action="append", default=[], metavar="EP", help="Zenoh endpoint to join (repeatable)")
    parser.add_argument("--run-id", help="key namespace of this run (default: random)")
    parser.add_argument("--backend", choices=("auto", "egl", "raycast"), help="renderer of local workers")
    parser.add_argument("--seed", type=int, default=0, help="seed of env, policy and sampling (default 0)")
    parser.add_argument("--out", help="run folder (default runs/TASK-<timestamp>)")
    parser.add_argument("--device", default="auto", help="torch device of the policy (default auto: cuda when torch sees a GPU, else cpu)")
    parser.add_argument("--worker-threads", type=int, default=None, metavar="N",
                        help="tracing threads of each local worker (default: the host's usable cores shared among the workers)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads of the trainer (default 1)")
    parser.add_argument("--update-threads", type=int, default=None, metavar="N",
                        help="threads of each PPO update, when the workers are idle; each minibatch is split "
                             "across them (default: every CPU or 1, whichever the updates are timed faster with)")
    parser.add_argument("--n-steps", type=int, help="rollout steps per env between updates")
    parser.add_argument("--batch-size", type=int, help="PPO minibatch size")
    parser.add_argument("--n-epochs", type=int, default=None,
                        help="passes over each rollout (default: the task's; 5, navigation 3)")
    parser.add_argument("--lr", type=float, help="learning rate (default 3e-4; per task for bptt/shac)")
    parser.add_argument("--gamma", type=float, default=0.99, help="discount (default 0.99)")
    parser.add_argument("--ent-coef", type=float, default=0.0, help="entropy bonus (default 0)")
    parser.add_argument("--log-std-init", type=float, help="initial log std of the action noise (default: per task)")
    parser.add_argument("--checkpoint-every", type=int, default=50_000, metavar="STEPS", help="0: only the final model")
    parser.add_argument("--video-every", type=int, default=None, metavar="STEPS",
                        help="film a deterministic episode every STEPS env steps in the background (videos/step-<n>.gif "
                             "and TensorBoard; 0: off; default: the host plan's, every tenth of the run from 8 cores, "
                             "off below, as it takes CPU from training)")
    parser.add_argument("--backbone", choices=BACKBONES, default="visfly-cnn", help="image backbone")
    parser.add_argument("--no-normalize", action="store_true", help="do not normalise vector observations and rewards")
    parser.add_argument("--overlap", action=argparse.BooleanOptionalAction, default=None,
                        help="ppo: step two agent groups in turn, the workers rendering one while the learner acts "
                             "on the other (no policy lag; default: the host plan's, on from 4 cores or with remote "
                             "workers only). sb3-ppo: collect the next rollout while PPO updates (policy lag of "
                             "one update); default: on when every worker is remote (--workers 0)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    add_scene_root(parser)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="env setting passed to make_env (repeatable)")
    add_zenoh_config_argument(parser)
    parser.add_argument("--algo", choices=ALGOS, help="ppo (PPO on the tensor env, rollout on the learner's "
                        "device), sb3-ppo (stable-baselines3's loop), or bptt / shac through the dynamics "
                        "(default: the task's, see visfly_dist.training.config.TASK_DEFAULTS)")
    parser.add_argument("--horizon", type=int, help="bptt/shac window, steps (default 32; per task)")
    parser.add_argument("--recurrent", action="store_true",
                        help="an LSTM between the extractor and the heads (sb3-contrib RecurrentPPO, SB3's loop; "
                             "with --algo ppo too, which says so); not with bptt/shac")
    parser.set_defaults(func=run)


def add_scene_root(parser: argparse.ArgumentParser) -> None:
    """``--scene-root DIR`` (repeatable): folders that scene paths in ``--set scenes=...`` are read from."""
    parser.add_argument("--scene-root", action="append", default=[], metavar="DIR",
                        help="folder scene files may be loaded from; scene paths are relative to it (repeatable)")


def scene_roots(args: argparse.Namespace) -> tuple[str, ...]:
    """The ``--scene-root`` folders as absolute paths (a run's config stays valid from any folder)."""
    return tuple(str(Path(r).resolve()) for r in args.scene_root)


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    """The TrainConfig the command line describes (unresolved: task defaults fill ``None``)."""
    return TrainConfig(
        task=args.task,
        timesteps=args.timesteps,
        num_envs=args.num_envs,
        workers=args.workers,
        connect=tuple(args.connect),
        run_id=args.run_id,
        backend=args.backend,
        seed=args.seed,
        out=args.out,
        device=args.device,
        worker_threads=args.worker_threads,
        threads=args.threads,
        update_threads=args.update_threads,
        n_steps=args.n_steps,
        batch_size=args.batch_size,
        lr=args.lr,
        n_epochs=args.n_epochs,
        gamma=args.gamma,
        ent_coef=args.ent_coef,
        log_std_init=args.log_std_init,
        checkpoint_every=args.checkpoint_every,
        video_every=args.video_every,
        backbone=args.backbone,
        normalize=not args.no_normalize,
        overlap=args.overlap,
        progress=not args.quiet,
        scene_roots=scene_roots(args),
        overrides=with_zenoh_config(dict(parse_override(item) for item in args.set), args.zenoh_config),
        algo=args.algo,
        horizon=args.horizon,
        recurrent=args.recurrent,
    )


def run(args: argparse.Namespace) -> int:
    cfg = config_from_args(args)
    algo = cfg.resolved().algo
    if algo == "bptt":
        from visfly_dist.training.bptt import train_bptt as train
    elif algo == "shac":
        from visfly_dist.training.shac import train_shac as train
    else:
        from visfly_dist.training.ppo import train
    stopped: list[int] = []
    handlers = {signum: signal.signal(signum, lambda signum, frame: _stop(stopped, signum))
                for signum in (signal.SIGINT, signal.SIGTERM)}
    stop.taken()
    try:
        result = train(cfg)
    except KeyboardInterrupt:
        if not stopped:
            raise
        print(f"interrupted (signal {stopped[0]}) before training began", file=sys.stderr, flush=True)
        return 128 + stopped[0]
    finally:
        for signum, previous in handlers.items():
            signal.signal(signum, previous)
        stop.taken()
    return 128 + stopped[0] if stopped else 130 if result.interrupted else 0


def _stop(stopped: list[int], signum: int) -> None:
    """Ctrl-C and SIGTERM (Slurm's time limit and preemption, ``kill``, ``timeout``) stop training:
    the trainer saves ``final.zip`` and closes its workers (:mod:`~visfly_dist.training.stop`)."""
    stopped.append(signum)
    stop.ask(signum)
