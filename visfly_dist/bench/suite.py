"""``visfly-dist bench all``: every benchmark in one run, with the peer beside ours.

Sections, in order (``--sections`` picks a subset):

* ``physics``: batched dynamics, agent-steps/s at 100, 1,000 and 10,000 agents, eager and
  ``torch.compile``, with and without autograd (:func:`visfly_dist.bench.physics.bench_physics`).
* ``render``: each backend at 64x64 and 256x256 (depth, RGB, segmentation; 100 cameras,
  garage-stones) and obstacle queries (:func:`visfly_dist.bench.render.bench_render`).
* ``end_to_end``: ``VecEnv.step`` env-steps/s of the navigation task with 1 and 2 workers, shared
  memory on and off, and where the time goes (:func:`visfly_dist.bench.step.bench_step`).
* ``scaling``: env-steps/s against scenes (1, 2, 4, 8) and workers (1, 2).
* ``peer``: gym-pybullet-drones-style pybullet physics at 100 drones and TinyRenderer depth
  (:mod:`visfly_dist.bench.peer`).

Then the ratios ours/peer against their goals. A section whose dependency is missing or which fails
is recorded with its error and the run goes on: one broken part never hides the others' figures.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import traceback
from dataclasses import dataclass
from typing import Any, Callable

from visfly_dist.bench import report
from visfly_dist.bench.common import Stopwatch, load_average, machine_info
from visfly_dist.errors import ConfigError

SECTIONS = ("physics", "render", "end_to_end", "scaling", "peer")
GOALS = {"physics": 10.0, "depth": 5.0, "quick_s": 600.0}
BUSY_LOAD = 0.5
"""Load average per core, before the run starts, above which the machine counts as busy."""


@dataclass(frozen=True)
class Sizes:
    """How much work each section does (a preset: ``full``, ``quick`` or ``tiny``)."""

    physics_agents: tuple[int, ...] = (100, 1_000, 10_000)
    physics_modes: tuple[str, ...] = ("eager", "compiled")
    physics_grads: tuple[bool, ...] = (False, True)
    physics_steps: int = 200
    physics_compiled_grad_agents: tuple[int, ...] = (100, 1_000, 10_000)
    """Agent counts of the compiled-with-grad configuration: compiling a backward pass takes minutes."""
    render_res: tuple[int, ...] = (64, 256)
    render_kinds: tuple[str, ...] = ("depth", "rgb", "segmentation")
    render_cameras: int = 100
    render_reps: int = 5
    step_agents: int = 100
    step_res: int = 64
    step_workers: tuple[int, ...] = (1, 2)
    step_shm: tuple[bool, ...] = (True, False)
    step_steps: int = 200
    scaling_scenes: tuple[int, ...] = (1, 2, 4, 8)
    scaling_workers: tuple[int, ...] = (1, 2)
    scaling_steps: int = 100
    peer_drones: tuple[int, ...] = (100, 1_000)
    """Drone counts of the peer's physics; the physics goal is set at the first."""
    peer_seconds: float = 5.0
    peer_res: tuple[int, ...] = (64, 256)
    peer_cameras: int = 100
    peer_reps: int = 3


PRESETS: dict[str, Sizes] = {
    "full": Sizes(),
    "quick": Sizes(physics_steps=100, physics_compiled_grad_agents=(100,), render_reps=2, step_steps=30,
                   scaling_steps=15, peer_seconds=3.0, peer_reps=1),
    "tiny": Sizes(physics_agents=(8,), physics_modes=("eager",), physics_grads=(False,), physics_steps=2,
                  render_res=(16,), render_kinds=("depth",), render_cameras=4, render_reps=1,
                  step_agents=4, step_res=16, step_workers=(1,), step_shm=(True,), step_steps=2,
                  scaling_scenes=(1, 2), scaling_workers=(1,), scaling_steps=2,
                  peer_drones=(4,), peer_seconds=0.05, peer_res=(16,), peer_cameras=4, peer_reps=1),
}


# -- sections --------------------------------------------------------------------------------------

def section_physics(sizes: Sizes, log: Callable[[str], None]) -> dict[str, Any]:
    """One ``bench_physics`` call per configuration, so that one failing configuration (a compiler
    error, say) costs only its own row: it is kept as ``{"agents", "mode", "grad", "error"}``."""
    import torch

    from visfly_dist.bench.physics import bench_physics

    rows: list[dict[str, Any]] = []
    for mode in sizes.physics_modes:
        for grad in sizes.physics_grads:
            for agents in sizes.physics_agents:
                if mode == "compiled" and grad and agents not in sizes.physics_compiled_grad_agents:
                    continue
                watch = Stopwatch()
                if mode == "compiled":
                    # Each configuration compiles afresh (its compile time is its own), and compiled
                    # variants of earlier configurations do not count against the recompile limit.
                    torch.compiler.reset()
                try:
                    row = bench_physics(agents=[agents], modes=[mode], grads=[grad], device="cpu",
                                        steps=sizes.physics_steps)[0]
                except Exception as exc:  # noqa: BLE001  (recorded in the row; the other rows still count)
                    row = {"agents": agents, "mode": mode, "grad": grad, "error": f"{type(exc).__name__}: {exc}"}
                    log(f"[bench all] !! physics {mode} grad={grad} {agents} agents FAILED: {row['error'][:300]}")
                rows.append(row)
                log(f"[bench all] physics {mode} grad={grad} {agents} agents: "
                    f"{fmt_rate(row.get('agent_steps_per_s'))} agent-steps/s ({watch.elapsed:.1f} s)")
    if all("error" in r for r in rows):
        raise RuntimeError(f"every physics configuration failed; first: {rows[0]['error']}")
    out: dict[str, Any] = {"rows": rows}
    skipped = [n for n in sizes.physics_agents if n not in sizes.physics_compiled_grad_agents]
    if "compiled" in sizes.physics_modes and True in sizes.physics_grads and skipped:
        out["note"] = (f"compiled with grad ran at {list(sizes.physics_compiled_grad_agents)} agents only (compiling "
                       f"the backward pass takes minutes per size); the full preset runs {skipped} too.")
    return out


def fmt_rate(value: float | None) -> str:
    return "-" if value is None else f"{value:,.0f}"


def section_render(sizes: Sizes, log: Callable[[str], None]) -> dict[str, Any]:
    from visfly_dist.bench.render import bench_render

    rows = bench_render(backends=None, res=list(sizes.render_res), kinds=list(sizes.render_kinds),
                        cameras=sizes.render_cameras, reps=sizes.render_reps, log=log)
    return {"rows": rows}


def section_end_to_end(sizes: Sizes, log: Callable[[str], None]) -> dict[str, Any]:
    from visfly_dist.bench.step import bench_step

    rows = []
    for shm in sizes.step_shm:
        rows += bench_step(agents=sizes.step_agents, workers=list(sizes.step_workers), res=sizes.step_res,
                           shm=shm, steps=sizes.step_steps, log=log)
    return {"rows": rows}


def section_scaling(sizes: Sizes, log: Callable[[str], None]) -> dict[str, Any]:
    from visfly_dist.bench.step import bench_step

    rows = []
    for scenes in sizes.scaling_scenes:
        rows += bench_step(agents=sizes.step_agents, workers=list(sizes.scaling_workers), res=sizes.step_res,
                           scenes=scenes, steps=sizes.scaling_steps, log=log)
    return {"rows": rows}


def section_peer(sizes: Sizes, log: Callable[[str], None]) -> dict[str, Any]:
    from visfly_dist.bench.peer import peer_depth, peer_physics
    from visfly_dist.scenes import generate_scene

    scene = generate_scene("garage-stones", seed=0)
    physics = []
    for drones in sizes.peer_drones:
        # The same simulated time at every size would take minutes at 1,000 drones; keep the wall time flat.
        seconds = sizes.peer_seconds * min(1.0, sizes.peer_drones[0] / drones)
        log(f"[bench all] peer: pybullet physics, {drones} drones, {seconds:g} s simulated")
        physics.append(peer_physics(drones, seconds))
    depth = []
    for res in sizes.peer_res:
        log(f"[bench all] peer: TinyRenderer depth {res}x{res}, {sizes.peer_cameras} cameras")
        depth.append(peer_depth(res, sizes.peer_cameras, scene, reps=sizes.peer_reps))
    return {"physics": physics, "depth": depth}


SECTION_FUNCS: dict[str, Callable[[Sizes, Callable[[str], None]], dict[str, Any]]] = {
    "physics": section_physics,
    "render": section_render,
    "end_to_end": section_end_to_end,
    "scaling": section_scaling,
    "peer": section_peer,
}


def run_section(name: str, sizes: Sizes, log: Callable[[str], None]) -> dict[str, Any]:
    """Run one section; a failure becomes ``{"status": "error", "error": ...}`` instead of an exception."""
    watch = Stopwatch()
    try:
        out = SECTION_FUNCS[name](sizes, log)
        out = {"status": "ok", **out}
    except ModuleNotFoundError as exc:
        out = {"status": "error", "error": f"missing dependency: {exc}", "traceback": traceback.format_exc()}
    except Exception as exc:  # noqa: BLE001  (a broken section is recorded; the run goes on)
        out = {"status": "error", "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
    out["elapsed_s"] = round(watch.elapsed, 2)
    if out["status"] != "ok":
        log(f"[bench all] !! section {name} FAILED after {out['elapsed_s']} s: {out['error']}")
    return out


# -- ratios ----------------------------------------------------------------------------------------

def _best(rows: list[dict[str, Any]], key: str, keep: Callable[[dict[str, Any]], bool]) -> dict[str, Any] | None:
    rows = [r for r in rows if keep(r) and isinstance(r.get(key), (int, float)) and r[key] > 0]
    return max(rows, key=lambda r: r[key]) if rows else None


def _physics_at(n: int, grad: bool) -> Callable[[dict[str, Any]], bool]:
    """Keeps the physics rows of ``n`` agents, with gradients or without."""
    return lambda r: r.get("agents") == n and bool(r.get("grad")) == grad


def compute_ratios(result: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Ours/peer for physics (sim-seconds/s at 100 drones) and 64x64 depth (our fastest backend)."""
    sections = result["sections"]
    ok = {k: v for k, v in sections.items() if v.get("status") == "ok"}
    peer = ok.get("peer", {})
    out: dict[str, dict[str, Any]] = {}

    # Physics: simulated seconds of the batch per wall second at the same number of drones. The goal
    # is set at the first peer size (100 drones); larger sizes show how each side scales.
    phys_rows = ok.get("physics", {}).get("rows", [])
    peer_rows = peer.get("physics", [])
    if not peer_rows or not phys_rows:
        out["physics sim-s/s"] = _ratio(None, None, GOALS["physics"], "needs the physics and peer sections")
    for i, p in enumerate(peer_rows):
        n = p["drones"]
        for grad in (False, True) if i == 0 else (False,):
            ours = _best(phys_rows, "sim_seconds_per_s", _physics_at(n, grad))
            label = f"physics sim-s/s, {n:,} drones" + (", ours with grad" if grad else "")
            note = (f"ours: {ours.get('mode')}" if ours else f"no physics row at {n} agents") + "; peer: pybullet 240 Hz"
            out[label] = _ratio(ours["sim_seconds_per_s"] if ours else None, p["sim_seconds_per_s"],
                                GOALS["physics"] if i == 0 and not grad else None, note)

    peer_depth = next((d for d in peer.get("depth", []) if d.get("res") == 64), None)
    render_rows = ok.get("render", {}).get("rows", [])
    ours = _best(render_rows, "frames_per_s", lambda r: r.get("kind") == "depth" and r.get("res") == 64)
    note = (f"64x64 depth; ours: {ours.get('backend')} ({ours.get('where', '')}); peer: TinyRenderer"
            if ours else "needs the render section at 64x64 depth and the peer")
    out["depth 64x64 frames/s"] = _ratio(ours["frames_per_s"] if ours else None,
                                         peer_depth["frames_per_s"] if peer_depth else None,
                                         GOALS["depth"], note)
    return out


def _ratio(ours: float | None, peer: float | None, goal: float | None, note: str) -> dict[str, Any]:
    ratio = ours / peer if ours and peer else None
    return {"ours": ours, "peer": peer, "ratio": ratio, "goal": goal, "goal_text": f">= {goal:g}x peer" if goal else "-",
            "met": None if ratio is None or goal is None else ratio >= goal, "note": note}


# -- the run ---------------------------------------------------------------------------------------

def run_suite(sizes: Sizes, sections: tuple[str, ...] = SECTIONS, *, preset: str = "custom",
              log: Callable[[str], None] = print, argv: list[str] | None = None) -> dict[str, Any]:
    """Run the chosen sections and return the result dictionary (see :mod:`visfly_dist.bench.report`)."""
    unknown = [s for s in sections if s not in SECTIONS]
    if unknown:
        raise ConfigError(f"unknown sections {unknown}; valid: {list(SECTIONS)}")
    watch = Stopwatch()
    result: dict[str, Any] = {"machine": machine_info(argv), "preset": preset, "sizes": dataclasses.asdict(sizes),
                              "sections": {}}
    for name in sections:
        log(f"[bench all] {name} ... (elapsed {watch.elapsed:.0f} s)")
        result["sections"][name] = run_section(name, sizes, log)
        log(f"[bench all] {name} {result['sections'][name]['status']} in {result['sections'][name]['elapsed_s']} s")
    result["ratios"] = compute_ratios(result)
    result["total_s"] = round(watch.elapsed, 1)
    result["load_average_end"] = load_average()
    if preset == "quick":
        result["ratios"]["--quick wall time (s)"] = {
            "ours": result["total_s"], "peer": None, "ratio": None, "goal": GOALS["quick_s"],
            "goal_text": f"<= {GOALS['quick_s']:g} s", "met": result["total_s"] <= GOALS["quick_s"],
            "note": "the whole --quick run, all sections"}
    result["busy_note"] = busy_note(result)
    return result


def busy_note(result: dict[str, Any]) -> str:
    """A warning when the load average says other work shared the machine during the run."""
    cores = result["machine"].get("cores") or 1
    start = result["machine"].get("load_average_start")
    end = result.get("load_average_end")
    # Before the run, any load is someone else's; at the end, this run's own workers (up to two
    # processes and the driver) account for about cores + 1.
    busy = (start and start[0] > BUSY_LOAD * cores) or (end and end[1] > cores + 1)
    if not busy:
        return ""
    return (f"the machine was busy (load average {start} at the start, {end} at the end, on {cores} cores; other "
            "engineers' tests ran concurrently): absolute figures are noisy, ratios (same run) less so")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="fewer steps and repetitions (within 10 minutes)")
    parser.add_argument("--tiny", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS), metavar="SECTION",
                        help=f"run only these sections (of: {', '.join(SECTIONS)})")
    parser.add_argument("--json", required=True, metavar="FILE", help="write the results here")
    parser.add_argument("--plots", metavar="DIR", help="write PNG plots into this folder")
    parser.add_argument("--md", metavar="FILE", help="write a Markdown report (e.g. BENCHMARKS.md)")


def run(args: argparse.Namespace) -> int:
    preset = "tiny" if args.tiny else "quick" if args.quick else "full"
    sections = tuple(s for s in SECTIONS if s in args.sections)

    def log(line: str) -> None:
        print(line, flush=True)

    result = run_suite(PRESETS[preset], sections, preset=preset, log=log)
    plots = report.write_plots(result, args.plots) if args.plots else []
    result["plots"] = [str(p) for p in plots]
    report.write_json(result, args.json)
    print()
    print(report.text_report(result))
    if result["busy_note"]:
        print(f"note: {result['busy_note']}")
    if args.md:
        report.write_markdown(result, args.md, args.plots or ".")
    print(f"wrote {args.json}" + (f", {len(plots)} plots in {args.plots}" if args.plots else "")
          + (f", {args.md}" if args.md else ""), flush=True)
    failed = [n for n, s in result["sections"].items() if s["status"] != "ok"]
    if failed:
        print(f"sections that failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0
