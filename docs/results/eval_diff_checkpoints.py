"""Deterministic evaluation of every checkpoint of BPTT/SHAC runs (lag-free, unlike the training
curve's mean over the last 100 episodes): one line per checkpoint, and ``RUN/eval_curve.csv``
(``timesteps,mean_return,success_rate``; ``plot_differentiable.py --eval-curve`` plots it).

    python docs/results/eval_diff_checkpoints.py hover runs/bptt-hover [RUN ...] --episodes 32 --seed 7
"""
import argparse
import csv
import re
from pathlib import Path

import torch

from visfly_dist.training.bptt import load_actor
from visfly_dist.training.evaluation import build_eval_env, evaluate, find_run_config

parser = argparse.ArgumentParser()
parser.add_argument("task")
parser.add_argument("runs", nargs="+", type=Path)
parser.add_argument("--episodes", type=int, default=32)
parser.add_argument("--seed", type=int, default=7)
parser.add_argument("--num-envs", type=int, default=16)
args = parser.parse_args()
torch.set_num_threads(1)
for run in args.runs:
    checkpoints = sorted(run.glob("checkpoints/step_*.npz"), key=lambda p: int(re.findall(r"\d+", p.stem)[0]))
    env = build_eval_env(args.task, args.num_envs, args.seed, find_run_config(run / "final.npz"), {}, {})
    rows = []
    try:
        for ckpt in checkpoints:
            actor = load_actor(ckpt, env.unwrapped, find_run_config(ckpt).backbone)
            stats = evaluate(actor, env, args.episodes, deterministic=True, seed=args.seed)
            rows.append((int(re.findall(r"\d+", ckpt.stem)[0]), f"{stats.mean_return:.3f}", f"{stats.success_rate:.3f}"))
            print(f"{run.name} {ckpt.stem:>12} return {stats.mean_return:7.2f} success {stats.success_rate:.2f}", flush=True)
    finally:
        env.close()
    with (run / "eval_curve.csv").open("w", newline="") as f:
        csv.writer(f).writerows([("timesteps", "mean_return", "success_rate"), *rows])
