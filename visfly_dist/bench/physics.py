"""``visfly-dist bench physics``: batched dynamics throughput, eager and compiled, with and without grad.

Times ``Quadrotor.step`` under CTBR (ctrl_dt 0.02 s, sim_dt 0.005 s, RK4, motor lag) at hover
commands. Without grad the loop only steps; with grad the actions require grad and every
``BPTT_HORIZON`` steps a loss on the positions is backpropagated and the state detached (truncated
BPTT), and the backward passes are part of the time.

Each JSON row: ``agents``, ``mode`` (eager|compiled), ``grad``, ``agent_steps_per_s`` (agents x
control steps per wall second), ``sim_seconds_per_s`` (simulated drone-seconds per wall
second: agents x simulated seconds), ``device``, ``steps``, ``seconds``, ``compile_s`` (first call, compiled mode), ``threads``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Sequence

import torch

from visfly_dist.dynamics import DynamicsConfig, Quadrotor
from visfly_dist.errors import ConfigError
from visfly_dist.output_paths import check_output_file
from visfly_dist.training.host_plan import check_device

MODES = ("eager", "compiled")
BPTT_HORIZON = 10
CTRL_DT, SIM_DT = 0.02, 0.005


def _rollout(quad: Quadrotor, action: torch.Tensor, steps: int, grad: bool) -> None:
    state = quad.initial_state(pos=torch.zeros(quad.num_agents, 3, device=quad.device) + 1.0)
    if not grad:
        with torch.no_grad():
            for _ in range(steps):
                state = quad.step(state, action)
        return
    done = 0
    while done < steps:
        chunk = min(BPTT_HORIZON, steps - done)
        for _ in range(chunk):
            state = quad.step(state, action)
        state.pos.square().sum().backward()
        state = state.detach()
        done += chunk


def bench_one(agents: int, mode: str, grad: bool, device: str = "cpu", steps: int = 100) -> dict:
    """Time ``steps`` control steps of ``agents`` drones; one result row (see module docstring)."""
    config = DynamicsConfig(controller="ctbr", ctrl_dt=CTRL_DT, sim_dt=SIM_DT, integrator="rk4",
                            motor_lag=True, compile=(mode == "compiled"))
    quad = Quadrotor(config, "visfly", num_agents=agents, device=device)
    action = quad.hover_action().expand(agents, 4).contiguous()
    if grad:
        action = action.clone().requires_grad_()
    t0 = time.perf_counter()
    _rollout(quad, action, min(steps, 2 * BPTT_HORIZON if grad else 3), grad)   # warm-up, compiles
    _sync(device)
    warm = time.perf_counter() - t0
    t0 = time.perf_counter()
    _rollout(quad, action, steps, grad)
    _sync(device)
    seconds = time.perf_counter() - t0
    return {
        "agents": agents, "mode": mode, "grad": grad,
        "agent_steps_per_s": agents * steps / seconds,
        "sim_seconds_per_s": agents * steps * CTRL_DT / seconds,
        "device": str(quad.device), "steps": steps, "seconds": seconds,
        "compile_s": warm if mode == "compiled" else None,
        "threads": torch.get_num_threads(),
        "controller": "ctbr", "integrator": "rk4", "ctrl_dt": CTRL_DT, "sim_dt": SIM_DT,
    }


def bench_physics(agents: Sequence[int], modes: Sequence[str] = MODES, grads: Sequence[bool] = (False, True),
                  device: str = "cpu", steps: int = 100, verbose: bool = False, threads: int | None = 1) -> list[dict]:
    """One row per (agents, mode, grad); see ``bench_one``.

    ``threads`` sets torch's intra-op threads for the run (restored after; None keeps them): the
    ops here last microseconds, and extra threads only add contention on a shared machine.

    Raises:
        ConfigError: an unknown mode, or agents/steps < 1.
    """
    bad = [m for m in modes if m not in MODES]
    if bad:
        raise ConfigError(f"unknown modes {bad}: use {list(MODES)}")
    if steps < 1 or any(n < 1 for n in agents):
        raise ConfigError(f"steps={steps} and agents={list(agents)} must be >= 1")
    rows = []
    previous = torch.get_num_threads()
    torch.set_num_threads(previous if threads is None else threads)
    try:
        for mode in modes:
            for grad in grads:
                for n in agents:
                    row = bench_one(n, mode, grad, device, steps)
                    if verbose:
                        print(_format_row(row), flush=True)
                    rows.append(row)
    finally:
        torch.set_num_threads(previous)
    return rows


def _sync(device: str) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


HEADER = f"{'agents':>7} {'mode':>9} {'grad':>5} {'agent-steps/s':>15} {'sim s/s':>9} {'compile s':>10}"


def _format_row(row: dict) -> str:
    compile_s = f"{row['compile_s']:.1f}" if row["compile_s"] is not None else "-"
    return (f"{row['agents']:>7} {row['mode']:>9} {str(row['grad']):>5} {row['agent_steps_per_s']:>15,.0f} "
            f"{row['sim_seconds_per_s']:>9.2f} {compile_s:>10}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--agents", type=int, nargs="+", default=None,
                        help="batch sizes (default 100 1000 10000; --quick: 100 1000)")
    parser.add_argument("--device", default="cpu", help="torch device (default cpu)")
    parser.add_argument("--steps", type=int, default=None,
                        help="timed control steps per row (default 100; --quick: 20)")
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES, help="eager and/or compiled")
    parser.add_argument("--no-compile", action="store_true", help="eager only (skip torch.compile)")
    parser.add_argument("--no-grad-rows", action="store_true", help="skip the rows with gradients")
    parser.add_argument("--quick", action="store_true", help="fewer agents and steps")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch intra-op threads (default 1: these ops are microseconds long, and "
                             "extra threads only add contention on a shared machine)")
    parser.add_argument("--json", type=Path, default=None, help="write the rows to this JSON file")


def run(args: argparse.Namespace) -> int:
    agents = args.agents or ([100, 1000] if args.quick else [100, 1000, 10000])
    steps = (20 if args.quick else 100) if args.steps is None else args.steps
    if args.threads < 1:
        raise ConfigError(f"--threads {args.threads} must be >= 1")
    if args.no_compile and "compiled" in args.modes and args.modes != list(MODES):
        raise ConfigError(f"--modes {' '.join(args.modes)} asks for compiled rows, which --no-compile skips; drop one")
    device = check_device(args.device)
    if args.json:
        check_output_file(args.json, "--json")
    modes = ["eager"] if args.no_compile else args.modes
    grads = (False,) if args.no_grad_rows else (False, True)
    print(f"physics: CTBR, ctrl_dt {CTRL_DT}, sim_dt {SIM_DT}, RK4, motor lag; device {device}, "
          f"{steps} steps, {args.threads} thread(s)")
    print(HEADER)
    rows = bench_physics(agents, modes, grads, device, steps, verbose=True, threads=args.threads)
    if args.json:
        args.json.write_text(json.dumps({"benchmark": "physics", "rows": rows}, indent=2))
        print(f"wrote {args.json}")
    return 0
