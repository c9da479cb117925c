"""``visfly-dist bench update``: the CPU cost of one PPO update with the default policy, alone.

The update is most of the default training loop's CPU time on a small host, and its wall time
swings with outside load (OpenMP threads waiting for a core); its CPU time per sample does not,
or much less. This benchmark fills SB3's rollout buffer with observations of the task's shapes
(images at random depths) and times ``PPO.train()`` with the task's default sizes: CPU seconds
and wall seconds per update, and the extractor's CPU milliseconds per sample (forward and
backward, all epochs). Nothing is stepped: the scene workers start once, only to read the
observation space.

Each thread count runs two ways (``--modes``): ``sharded``, the update ``visfly-dist train`` runs
(each minibatch split across the threads, one torch thread each;
:mod:`visfly_dist.training.parallel_update`), and ``openmp``, SB3's own ``PPO.train`` with that many
torch threads.

With ``--compare-kernels`` the same measurement runs again in a child process with the native
training kernels off (``VISFLY_NATIVE_KERNELS=0``), and the ratio is reported.

``--backbones NAME... | all`` adds, per image backbone (``--backbone`` of train) and image kind
(``--images depth rgb``: 64x64 depth in metres, 64x64 RGB), the image encoder's cost alone:
CPU milliseconds per image of a forward and backward pass (training) and of a forward pass without
gradients (rollouts), at a batch of ``--backbone-batch`` on one torch thread, and its parameters
(``--skip-update`` leaves the PPO rows out, so no scene worker starts).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from typing import Any, cast

import numpy as np

from visfly_dist.bench.common import load_average, machine_info


def observation_space(task: str) -> Any:
    """The task's observation space (a short-lived env with one local worker)."""
    from visfly_dist import make_env

    env = make_env(task, num_envs=1)
    try:
        return env.observation_space
    finally:
        env.close()


MODES = ("sharded", "openmp")


def bench_update(task: str = "navigation", threads: int = 1, reps: int = 3, seed: int = 0,
                 mode: str = "sharded") -> dict[str, Any]:
    """Time ``reps`` PPO updates of ``task``'s default configuration on ``threads`` threads.

    Returns:
        ``task, mode, threads, samples, epochs, batch_size, kernels, update_cpu_s, update_wall_s,
        ms_per_sample_pass`` (CPU ms per sample per epoch; medians over ``reps``).
    """
    import torch
    from gymnasium import spaces
    from stable_baselines3 import PPO
    from stable_baselines3.common.buffers import DictRolloutBuffer
    from stable_baselines3.common.vec_env import VecEnv

    from visfly_dist.training.config import TrainConfig
    from visfly_dist.training.extractors import visfly_policy_kwargs
    from visfly_dist.training.memory import keep_freed_memory
    from visfly_dist.training.native_kernels import load_kernels
    from visfly_dist.training.parallel_update import sharded_ppo_train

    keep_freed_memory()
    cfg = TrainConfig(task=task, algo="ppo").resolved()
    assert (cfg.n_steps is not None and cfg.batch_size is not None and cfg.num_envs is not None
            and cfg.n_epochs is not None)  # the task's defaults
    obs_space = observation_space(task)
    action_space = spaces.Box(-1.0, 1.0, (4,), np.float32)
    torch.manual_seed(seed)
    # SB3 takes env=None (BaseAlgorithm does, and load() passes it); PPO's annotation leaves it out
    model = PPO("MultiInputPolicy", cast(VecEnv, None), n_steps=cfg.n_steps, batch_size=cfg.batch_size, n_epochs=cfg.n_epochs,
                policy_kwargs=visfly_policy_kwargs(cfg.backbone), seed=seed, device="cpu", verbose=0,
                _init_setup_model=False)
    # no env: PPO only needs the spaces and the number of envs to build its policy and buffer
    model.observation_space, model.action_space, model.n_envs = obs_space, action_space, cfg.num_envs
    model._setup_model()
    model.set_logger(_null_logger())
    rng = np.random.default_rng(seed)
    buf = model.rollout_buffer
    assert isinstance(buf, DictRolloutBuffer)  # a Dict observation space
    for _ in range(cfg.n_steps):
        obs = {k: _sample(space, cfg.num_envs, rng) for k, space in obs_space.spaces.items()}
        with torch.no_grad():
            actions, values, log_probs = model.policy({k: torch.as_tensor(v) for k, v in obs.items()})
        buf.add(obs, actions.numpy(), rng.normal(size=cfg.num_envs).astype(np.float32),
                np.zeros(cfg.num_envs, dtype=bool), values, log_probs)
    buf.compute_returns_and_advantage(last_values=torch.zeros(cfg.num_envs), dones=np.zeros(cfg.num_envs, dtype=bool))
    previous = torch.get_num_threads()
    torch.set_num_threads(threads if mode == "openmp" else 1)

    def update() -> None:
        if mode == "openmp":
            model.train()
        else:
            sharded_ppo_train(model, threads)

    cpu, wall = [], []
    try:
        update()  # warm-up: allocations, the first channels-last switch
        for _ in range(reps):
            c, w = time.process_time(), time.perf_counter()
            update()
            cpu.append(time.process_time() - c)
            wall.append(time.perf_counter() - w)
    finally:
        torch.set_num_threads(previous)
    samples = cfg.n_steps * cfg.num_envs
    update_cpu = float(np.median(cpu))
    return {"task": task, "mode": mode, "threads": threads, "samples": samples, "epochs": cfg.n_epochs, "batch_size": cfg.batch_size,
            "kernels": "native" if load_kernels()[0] is not None else "torch",
            "update_cpu_s": round(update_cpu, 3), "update_wall_s": round(float(np.median(wall)), 3),
            "ms_per_sample_pass": round(update_cpu / (samples * cfg.n_epochs) * 1e3, 6)}


IMAGES = {"depth": ((1, 64, 64), "float32", 20.0), "rgb": ((3, 64, 64), "uint8", 255.0)}
"""Image kinds of ``bench_backbone``: shape, dtype, upper bound."""


def bench_backbone(backbone: str, image: str = "depth", batch: int = 256, reps: int = 3, seed: int = 0) -> dict[str, Any]:
    """CPU cost per image of ``backbone``'s image encoder (normaliser, trunk, linear to 128), one torch thread.

    Returns:
        ``backbone, image, params, batch, fwd_bwd_ms_per_image`` (forward and backward, as in a PPO
        update) and ``forward_ms_per_image`` (no gradients, as in a rollout); CPU time, medians over ``reps``.
    """
    import torch
    from gymnasium import spaces

    from visfly_dist.training.extractors import ImageEncoder

    shape, dtype, high = IMAGES[image]
    space = spaces.Box(0, high, shape, np.dtype(dtype))
    torch.manual_seed(seed)
    encoder = ImageEncoder(space, backbone, "linear", image)
    x = torch.as_tensor(_sample(space, batch, np.random.default_rng(seed)))
    previous = torch.get_num_threads()
    torch.set_num_threads(1)

    def train_pass() -> None:
        encoder.zero_grad(set_to_none=True)
        encoder(x).square().mean().backward()

    def forward_pass() -> None:
        with torch.no_grad():
            encoder(x)

    timings: dict[str, float] = {}
    try:
        for name, fn in (("fwd_bwd_ms_per_image", train_pass), ("forward_ms_per_image", forward_pass)):
            fn()  # warm-up: allocations, the channels-last switch
            cpu = []
            for _ in range(reps):
                c = time.process_time()
                fn()
                cpu.append(time.process_time() - c)
            timings[name] = round(float(np.median(cpu)) / batch * 1e3, 4)
    finally:
        torch.set_num_threads(previous)
    return {"backbone": backbone, "image": image, "params": sum(p.numel() for p in encoder.parameters()),
            "batch": batch, **timings}


def _sample(space: Any, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` observations: images uniform in their range (depth up to 20 m), vectors standard normal."""
    if len(space.shape) == 3:
        high = 255.0 if space.dtype == np.uint8 else float(np.minimum(space.high, 20.0).max())
        return rng.uniform(0.0, high, size=(n, *space.shape)).astype(space.dtype)
    return rng.normal(size=(n, *space.shape)).astype(space.dtype)


def _null_logger() -> Any:
    from stable_baselines3.common.logger import Logger

    return Logger(folder=None, output_formats=[])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--task", default="navigation", help="task whose default PPO update to time (default: navigation)")
    parser.add_argument("--threads", type=int, nargs="+", default=[1], help="torch threads to try (default 1)")
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES),
                        help="sharded: the update visfly-dist train runs; openmp: SB3's PPO.train on torch threads "
                             "(default: both)")
    parser.add_argument("--reps", type=int, default=3, help="timed updates per row (median; default 3)")
    parser.add_argument("--compare-kernels", action="store_true",
                        help="also run with the native training kernels off, in a child process")
    parser.add_argument("--backbones", nargs="+", metavar="NAME",
                        help="also time these image backbones alone (names of train's --backbone, or all)")
    parser.add_argument("--images", nargs="+", choices=tuple(IMAGES), default=list(IMAGES),
                        help="image kinds of --backbones (default: depth rgb, both 64x64)")
    parser.add_argument("--backbone-batch", type=int, default=256, help="batch of --backbones (default 256)")
    parser.add_argument("--skip-update", action="store_true", help="only the --backbones rows (no scene worker starts)")
    parser.add_argument("--json", metavar="FILE", help="write the rows and the machine info here")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    from visfly_dist.bench import report
    from visfly_dist.errors import ConfigError
    from visfly_dist.training.config import BACKBONES

    if any(t < 1 for t in args.threads) or args.reps < 1 or args.backbone_batch < 1:
        raise ConfigError(f"--threads {args.threads}, --reps {args.reps} and --backbone-batch {args.backbone_batch} must be >= 1")
    backbones = list(BACKBONES) if args.backbones == ["all"] else list(args.backbones or [])
    unknown = [b for b in backbones if b not in BACKBONES]
    if unknown or (args.skip_update and not backbones):
        raise ConfigError(f"--backbones {args.backbones}: give some of {list(BACKBONES)} or 'all' "
                          f"(--skip-update needs them)")
    backbone_rows = [bench_backbone(b, image, args.backbone_batch, args.reps) for b in backbones for image in args.images]
    if args.skip_update:
        result: dict[str, Any] = {"machine": machine_info(), "rows": [], "backbones": backbone_rows, "load_average_end": load_average()}
        print(report.text_table(backbone_rows))
        if args.json:
            report.write_json(result, args.json)
            print(f"wrote {args.json}")
        return 0
    rows = [bench_update(args.task, t, args.reps, mode=m) for m in args.modes for t in args.threads]
    if args.child:
        print(json.dumps(rows))
        return 0
    if args.compare_kernels:
        command = [sys.executable, "-m", "visfly_dist.cli", "bench", "update", "--task", args.task, "--reps", str(args.reps),
                   "--child", "--modes", *args.modes, "--threads", *map(str, args.threads)]
        child = subprocess.run(command, env={**os.environ, "VISFLY_NATIVE_KERNELS": "0"}, capture_output=True, text=True,
                               check=True)
        rows += json.loads(child.stdout.strip().splitlines()[-1])
    result = {"machine": machine_info(), "rows": rows, "load_average_end": load_average()}
    print(report.text_table(rows))
    if backbone_rows:
        result["backbones"] = backbone_rows
        print(report.text_table(backbone_rows))
    if args.json:
        report.write_json(result, args.json)
        print(f"wrote {args.json}")
    return 0
