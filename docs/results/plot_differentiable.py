"""Plot the mean return of several ``visfly-dist train`` runs on one figure, and print the env steps
and wall time each took to first reach a given return.

    python docs/results/plot_differentiable.py OUT.png --target 50 ppo=runs/ppo-hover bptt=runs/bptt-hover ...

Reads each run folder's ``success_curve.csv`` (return over the last 100 episodes against env steps)
and ``progress.csv`` (``charts/steps_per_second``, the run's average so far, gives the wall time).
With ``--eval-curve`` it reads ``eval_curve.csv`` instead (deterministic evaluation of each
checkpoint, written by ``eval_diff_checkpoints.py``), on a log step axis (linear below 1k); ``--mark LABEL=STEPS:RETURN``
adds a reference point (e.g. PPO's final model). ``--metric success`` plots and targets the
success rate instead of the return.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
from matplotlib import pyplot as plt  # noqa: E402


def read_rows(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


def wall_seconds(run: Path, steps: int) -> float:
    """Wall seconds the run took to ``steps`` env steps, from its progress log (``time/*`` columns,
    else the run's final average steps per second)."""
    rows = read_rows(run / "progress.csv")
    for row in rows:
        if row.get("time/total_timesteps") and float(row["time/total_timesteps"]) >= steps and row.get("time/time_elapsed"):
            return float(row["time/time_elapsed"])
    rates = [float(r["charts/steps_per_second"]) for r in rows if r.get("charts/steps_per_second")]
    return steps / rates[-1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("runs", nargs="+", help="LABEL=RUN_FOLDER")
    parser.add_argument("--target", type=float, required=True, help="return to report steps and time to")
    parser.add_argument("--title", default="hover from state")
    parser.add_argument("--eval-curve", action="store_true", help="plot eval_curve.csv (checkpoint evaluations)")
    parser.add_argument("--metric", choices=("return", "success"), default="return", help="what to plot and target")
    parser.add_argument("--mark", action="append", default=[], metavar="LABEL=STEPS:RETURN", help="a reference point")
    args = parser.parse_args()
    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    for item in args.mark:
        label, point = item.split("=", 1)
        steps, ret = (float(x) for x in point.split(":"))
        ax.plot([steps], [ret], marker="*", ms=12, ls="none", label=label)
    for item in args.runs:
        label, folder = item.split("=", 1)
        run = Path(folder)
        curve = read_rows(run / ("eval_curve.csv" if args.eval_curve else "success_curve.csv"))
        steps = [int(r["timesteps"]) for r in curve]
        returns = [float(r["mean_return" if args.metric == "return" else "success_rate"]) for r in curve]
        ax.plot(steps, returns, label=label, marker="." if args.eval_curve else None)
        hit = next((i for i, r in enumerate(returns) if r >= args.target), None)
        final = f"final {args.metric} {returns[-1]:.2f} at {steps[-1]:,} steps, {wall_seconds(run, steps[-1]):.0f} s"
        if hit is None:
            print(f"{label}: never reached {args.target}; {final}")
        else:
            print(f"{label}: {args.metric} >= {args.target} first at {steps[hit]:,} env steps, "
                  f"{wall_seconds(run, steps[hit]):.0f} s wall; {final}")
    ax.axhline(args.target, color="grey", lw=0.8, ls="--")
    ylabel = f"deterministic eval {args.metric}" if args.eval_curve else f"mean {args.metric} (last 100 episodes)"
    ax.set(xlabel="env steps (all agents)", ylabel=ylabel, title=args.title)
    if args.eval_curve:
        ax.set_xscale("symlog", linthresh=1000)
        ax.set_xlim(left=0)
        ax.set_xticks([0, 1000, 10_000, 100_000])
    ax.xaxis.set_major_formatter(lambda x, _: f"{x / 1000:g}k")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.savefig(args.out, dpi=90)


if __name__ == "__main__":
    main()
