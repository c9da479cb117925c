"""SB3 callbacks of a training run: success rate and returns, progress lines, the success curve.

``SuccessCallback`` reads finished episodes from the step infos (``info["episode"]`` from
``VecMonitor``, ``info["is_success"]`` from the task), keeps the last ``window`` of them (an
episode cut because its worker was lost counts only among the end causes), and at the
end of every rollout logs ``charts/success_rate``, ``charts/mean_return``, ``charts/mean_length`` and
``charts/steps_per_second`` and, per end cause (see :mod:`visfly_dist.tasks.outcomes`), the share
of the window's episodes that ended so as ``ends/<cause>``; it appends a row to
``success_curve.csv`` and prints a progress line (with the most common end causes). At the end of
training it draws ``success_curve.png``.
"""

from __future__ import annotations

import csv
import sys
import time
from collections import deque
from pathlib import Path

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

from visfly_dist.tasks.outcomes import END_CAUSES, end_cause
from visfly_dist.training import stop

CURVE_FIELDS = ("timesteps", "success_rate", "mean_return", "mean_length", "episodes")


class SuccessCallback(BaseCallback):
    """Tracks success rate and return over the last ``window`` episodes; writes the curve.

    Args:
        run_dir: folder of ``success_curve.csv`` and ``success_curve.png``.
        total_timesteps: the run's budget, for the progress line.
        window: episodes averaged in each reported figure.
        print_every_s: least seconds between progress lines (0 prints every rollout).
        verbose: 0 prints nothing.
    """

    def __init__(self, run_dir: Path, total_timesteps: int, window: int = 100, print_every_s: float = 5.0, verbose: int = 1) -> None:
        super().__init__(verbose)
        self.run_dir = Path(run_dir)
        self.total = total_timesteps
        self.episodes: deque[tuple[float, float, float]] = deque(maxlen=window)
        self.causes: deque[str] = deque(maxlen=window)
        self.episodes_total = 0
        self.lost_total = 0  # episodes cut because their worker was lost (not in the figures above)
        self.print_every_s = print_every_s
        self.csv_path = self.run_dir / "success_curve.csv"
        self._t0 = 0.0
        self._steps0 = 0
        self._last_print = 0.0

    def _on_training_start(self) -> None:
        self._t0 = time.perf_counter()
        self._steps0 = self.num_timesteps
        with self.csv_path.open("w", newline="") as f:
            csv.writer(f).writerow(CURVE_FIELDS)

    def _on_step(self) -> bool:
        for done, info in zip(self.locals["dones"], self.locals["infos"]):
            if done and "episode" in info:
                self.record_episode(info)
        return True

    def record_episode(self, info: dict) -> None:
        """Count one finished episode from its last step's info (``episode``: ``r`` and ``l``, the
        end flags); trainers that do not go through SB3's loop call it directly."""
        ep = info["episode"]
        cause = end_cause(info, int(ep["l"]), self._max_episode_steps())
        self.causes.append(cause)
        if cause == "lost":  # cut by a failed worker or link: neither a success nor a failure
            self.lost_total += 1
            return
        self.episodes.append((float(bool(info.get("is_success", False))), float(ep["r"]), float(ep["l"])))
        self.episodes_total += 1

    def _max_episode_steps(self) -> int | None:
        config = getattr(self.training_env.unwrapped, "config", None)
        return getattr(config, "max_episode_steps", None)

    def cause_shares(self) -> dict[str, float]:
        """Share of the window's episodes per end cause (every cause, zeros included)."""
        n = max(len(self.causes), 1)
        return {c: sum(x == c for x in self.causes) / n for c in END_CAUSES}

    def summary(self) -> dict[str, float]:
        """Success rate, mean return and mean length over the window (NaN before any episode)."""
        if not self.episodes:
            return dict(success_rate=float("nan"), mean_return=float("nan"), mean_length=float("nan"))
        arr = np.asarray(self.episodes)
        return dict(success_rate=float(arr[:, 0].mean()), mean_return=float(arr[:, 1].mean()), mean_length=float(arr[:, 2].mean()))

    def _on_rollout_end(self) -> None:
        elapsed = max(time.perf_counter() - self._t0, 1e-9)
        sps = (self.num_timesteps - self._steps0) / elapsed
        self.logger.record("charts/steps_per_second", sps)
        if not self.episodes:
            return
        s = self.summary()
        for key, value in s.items():
            self.logger.record(f"charts/{key}", value)
        shares = self.cause_shares()
        for cause, share in shares.items():
            self.logger.record(f"ends/{cause}", share)
        with self.csv_path.open("a", newline="") as f:
            csv.writer(f).writerow(
                (self.num_timesteps, f"{s['success_rate']:.4f}", f"{s['mean_return']:.4f}", f"{s['mean_length']:.1f}", self.episodes_total)
            )
        now = time.perf_counter()
        if self.verbose and now - self._last_print >= self.print_every_s:
            self._last_print = now
            eta = (self.total - self.num_timesteps) / max(sps, 1e-9)
            top = sorted(((v, c) for c, v in shares.items() if v > 0), reverse=True)[:2]
            ends = ", ".join(f"{c} {v:.2f}" for v, c in top)
            lost = f" (+{self.lost_total} lost)" if self.lost_total else ""
            print(
                f"[{self.num_timesteps:>9,}/{self.total:,}] {sps:6.0f} steps/s  "
                f"success {s['success_rate']:.2f}  return {s['mean_return']:8.2f}  "
                f"length {s['mean_length']:6.1f}  episodes {self.episodes_total}{lost}  eta {eta / 60:5.1f} min  ends: {ends}",
                flush=True,
                file=sys.stdout,
            )

    def _on_training_end(self) -> None:
        plot_success_curve(self.csv_path, self.run_dir / "success_curve.png", self.episodes.maxlen or 0)


def read_curve(csv_path: Path) -> dict[str, np.ndarray]:
    """The columns of a ``success_curve.csv`` as float arrays."""
    with Path(csv_path).open() as f:
        rows = list(csv.DictReader(f))
    return {k: np.asarray([float(r[k]) for r in rows], dtype=np.float64) for k in CURVE_FIELDS}


def plot_success_curve(csv_path: Path, png_path: Path, window: int = 100) -> Path:
    """Success rate and mean return (over the last ``window`` episodes) against timesteps, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    curve = read_curve(csv_path)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.5), constrained_layout=True)
    ax1.plot(curve["timesteps"], curve["success_rate"], color="tab:green")
    ax1.set(xlabel="timesteps", ylabel="success rate", ylim=(-0.02, 1.02), title=f"success rate (last {window} episodes)")
    ax2.plot(curve["timesteps"], curve["mean_return"], color="tab:blue")
    ax2.set(xlabel="timesteps", ylabel="mean return", title=f"episode return (last {window} episodes)")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.xaxis.set_major_formatter(lambda x, _: f"{x / 1000:g}k")
    fig.savefig(png_path, dpi=100)
    plt.close(fig)
    return Path(png_path)


class StopWhenAsked(BaseCallback):
    """SB3's loop: raise, after each rollout, a stop (Ctrl-C, SIGTERM) swallowed on its way
    (:mod:`~visfly_dist.training.stop`)."""

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        stop.raise_if_asked()
