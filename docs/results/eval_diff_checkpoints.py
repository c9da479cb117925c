"""Deterministic evaluation of every checkpoint of BPTT/SHAC runs (lag-free, unlike the training
curve's mean over the last 100 episodes): one line per checkpoint, env steps and mean return.

    python docs/results/eval_diff_checkpoints.py hover runs/bptt-hover [RUN ...] --episodes 32 --seed 7
"""
import argparse
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
    try:
        for ckpt in checkpoints + [run / "final.npz"]:
            actor = load_actor(ckpt, env.unwrapped, find_run_config(ckpt).backbone)
            stats = evaluate(actor, env, args.episodes, deterministic=True, seed=args.seed)
            print(f"{run.name} {ckpt.stem:>12} return {stats.mean_return:7.2f} success {stats.success_rate:.2f}", flush=True)
    finally:
        env.close()
