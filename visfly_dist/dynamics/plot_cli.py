"""``visfly-dist plot step-response``: PS and LV step responses from random initial states.

Writes ``ps_step_response.png`` and ``lv_step_response.png``: position, attitude (roll, pitch,
yaw), velocity and body rates over time, one colour per initial state, the command dashed.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch

from visfly_dist.dynamics.config import DynamicsConfig
from visfly_dist.dynamics.quadrotor import Quadrotor
from visfly_dist.dynamics.rotations import euler_from_quat
from visfly_dist.dynamics.sampler import Distribution, InitialStateSampler
from visfly_dist.errors import ConfigError
from visfly_dist.output_paths import check_output_dir

ORIGIN = (0.0, 0.0, 2.0)
# Commands as actions: PS to (1, -1, 2.5) m with yaw 0.6 rad; LV at (1.5, -1, 0.5) m/s, yaw 0.6 rad.
COMMANDS = {
    "ps": (0.1, -0.1, 0.05, 0.6 / torch.pi),
    "lv": (0.15, -0.1, 0.05, 0.6 / torch.pi),
}
DEFAULT_SAMPLER = InitialStateSampler(
    pos=Distribution("uniform", b=(0.5, 0.5, 0.5)),
    vel=Distribution("uniform", b=(1.0, 1.0, 0.5)),
    orientation=Distribution("uniform", b=(0.4, 0.4, 0.8)),
    omega=Distribution("uniform", b=(1.0, 1.0, 1.0)),
)


def simulate_step_response(controller: str, agents: int = 6, seed: int = 0, duration: float = 5.0,
                           airframe: str = "visfly") -> dict[str, torch.Tensor]:
    """Fly ``agents`` drones from random initial states under one constant PS or LV command.

    Returns:
        ``time`` (T,) s, ``pos``/``vel``/``euler``/``omega`` (T, agents, 3) including the initial
        state, and ``target`` (4,): the commanded position or velocity and the yaw angle.
    """
    config = DynamicsConfig(controller=controller, position_origin=ORIGIN)
    quad = Quadrotor(config, airframe, num_agents=agents, dtype=torch.float64)
    sample = DEFAULT_SAMPLER.sample(agents, torch.Generator().manual_seed(seed), torch.float64)
    state = quad.initial_state(pos=sample.pos + torch.tensor(ORIGIN, dtype=torch.float64), vel=sample.vel,
                               quat=sample.quat, omega=sample.omega)
    action = torch.tensor(COMMANDS[controller], dtype=torch.float64).expand(agents, 4)
    frames = [state]
    for _ in range(round(duration / config.ctrl_dt)):
        state = quad.step(state, action)
        frames.append(state)
    scale = 10.0
    offset = torch.tensor(ORIGIN if controller == "ps" else (0.0, 0.0, 0.0), dtype=torch.float64)
    target = torch.cat((offset + scale * action[0, :3], action[0, 3:] * torch.pi))
    return {
        "time": torch.arange(len(frames), dtype=torch.float64) * config.ctrl_dt,
        "pos": torch.stack([f.pos for f in frames]),
        "vel": torch.stack([f.vel for f in frames]),
        "euler": torch.stack([euler_from_quat(f.quat) for f in frames]),
        "omega": torch.stack([f.omega for f in frames]),
        "target": target,
    }


def plot_step_response(controller: str, response: dict[str, torch.Tensor], path: Path) -> None:
    """Draw one 4x3 figure of a response from ``simulate_step_response`` to ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [("pos", "position [m]", ("x", "y", "z")),
            ("euler", "attitude [rad]", ("roll", "pitch", "yaw")),
            ("vel", "velocity [m/s]", ("vx", "vy", "vz")),
            ("omega", "body rate [rad/s]", ("p", "q", "r"))]
    commanded_row = "pos" if controller == "ps" else "vel"
    t = response["time"].numpy()
    fig, axes = plt.subplots(4, 3, figsize=(12, 10), sharex=True)
    colours = plt.get_cmap("tab10")
    for r, (key, label, names) in enumerate(rows):
        data = response[key].numpy()
        for c in range(3):
            ax = axes[r, c]
            for agent in range(data.shape[1]):
                ax.plot(t, data[:, agent, c], color=colours(agent % 10), lw=1.2)
            if key == commanded_row:
                ax.axhline(float(response["target"][c]), color="k", ls="--", lw=1)
            if key == "euler" and c == 2:
                ax.axhline(float(response["target"][3]), color="k", ls="--", lw=1)
            ax.set_title(names[c], fontsize=10)
            ax.grid(alpha=0.3)
            if c == 0:
                ax.set_ylabel(label)
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    title = {"ps": "PS: position + yaw step", "lv": "LV: velocity + yaw step"}[controller]
    fig.suptitle(f"{title} from {data.shape[1]} random initial states (dashed: command)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


MAX_DURATION_S = 600.0
"""Longest step response plotted: 20,000 control steps, a few seconds of compute."""


def run_step_response(args: argparse.Namespace) -> int:
    if not (math.isfinite(args.duration) and 0 < args.duration <= MAX_DURATION_S):
        raise ConfigError(f"--duration {args.duration} must be in (0, {MAX_DURATION_S:g}] seconds")
    out = check_output_dir(args.out, "--out")
    torch.set_num_threads(1)            # tiny batches: a second thread only adds contention
    for controller in ("ps", "lv"):
        response = simulate_step_response(controller, args.agents, args.seed, args.duration, args.airframe)
        path = out / f"{controller}_step_response.png"
        plot_step_response(controller, response, path)
        print(f"wrote {path}")
    return 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="plot", metavar="PLOT", required=True)
    p = sub.add_parser("step-response", help="PS and LV step responses (PNG)",
                       description="PS and LV step responses from random initial states (PNG).")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--agents", type=int, default=6, help="initial states, one colour each (default 6)")
    p.add_argument("--seed", type=int, default=0, help="seed of the initial states (default 0)")
    p.add_argument("--duration", type=float, default=5.0, help="seconds simulated (default 5)")
    p.add_argument("--airframe", default="visfly", help="airframe name or JSON path (default visfly)")
    p.set_defaults(func=run_step_response)
