"""Presenting a benchmark run: text tables, the JSON file, PNG plots and BENCHMARKS.md.

Everything here reads the result dictionary that :mod:`visfly_dist.bench.suite` builds:
``{"machine": {...}, "sizes": {...}, "sections": {name: {"status", "elapsed_s", "rows" | ..., "error"}},
"ratios": {...}, "total_s": ...}``. A section that failed has ``status == "error"`` and no figures;
every function here shows that instead of failing itself.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from visfly_dist.bench.common import STAGES

PLOT_FILES = {
    "render": "render_fps_vs_resolution.png",
    "scaling": "step_scaling.png",
    "stages": "step_stages.png",
    "physics": "physics_scaling.png",
}


def fmt(value: Any) -> str:
    """A table cell: floats with 3 significant figures (thousands separated), the rest as text."""
    if isinstance(value, bool) or value is None:
        return "-" if value is None else ("yes" if value else "no")
    if isinstance(value, float):
        if math.isnan(value) or math.isinf(value):
            return str(value)
        if abs(value) >= 1000:
            return f"{value:,.0f}"
        if abs(value) >= 1 or value == 0:
            return f"{value:.3g}" if abs(value) < 100 else f"{value:.0f}"
        return f"{value:.3g}"
    if isinstance(value, int):
        return f"{value:,}" if abs(value) >= 10_000 else str(value)
    if isinstance(value, Mapping):
        return " ".join(f"{k}={fmt(v)}" for k, v in value.items())
    return str(value)


def columns_of(rows: Sequence[Mapping[str, Any]], skip: Iterable[str] = ()) -> list[str]:
    """Keys of ``rows`` in order of first appearance, without ``skip``."""
    skip = set(skip)
    out: list[str] = []
    for row in rows:
        out.extend(k for k in row if k not in out and k not in skip)
    return out


def text_table(rows: Sequence[Mapping[str, Any]], columns: Sequence[str] | None = None) -> str:
    """Rows as an aligned plain-text table (missing cells show ``-``)."""
    if not rows:
        return "(no rows)"
    columns = list(columns or columns_of(rows))
    cells = [[fmt(row.get(c)) for c in columns] for row in rows]
    widths = [max(len(c), *(len(r[i]) for r in cells)) for i, c in enumerate(columns)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(columns, widths)),
             "  ".join("-" * w for w in widths)]
    lines += ["  ".join(v.rjust(w) for v, w in zip(r, widths)) for r in cells]
    return "\n".join(lines)


def markdown_table(rows: Sequence[Mapping[str, Any]], columns: Sequence[str] | None = None) -> str:
    """Rows as a GitHub Markdown table."""
    if not rows:
        return "_no rows_"
    columns = list(columns or columns_of(rows))
    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    lines += ["| " + " | ".join(fmt(row.get(c)).replace("|", "/") for c in columns) + " |" for row in rows]
    return "\n".join(lines)


def flat_rows(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Rows with nested maps flattened one level (``stages.physics``) for tables."""
    out = []
    for row in rows:
        flat: dict[str, Any] = {}
        for k, v in row.items():
            if isinstance(v, Mapping):
                flat.update({f"{k}.{kk}": vv for kk, vv in v.items()})
            else:
                flat[k] = v
        out.append(flat)
    return out


def write_json(result: Mapping[str, Any], path: str | os.PathLike) -> Path:
    """Write the result as indented JSON (non-finite floats become null); return the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(_finite(result), indent=2, sort_keys=False) + "\n")
    return path


def _finite(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Mapping):
        return {str(k): _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def _section_rows(result: Mapping[str, Any], name: str) -> list[dict[str, Any]]:
    section = result.get("sections", {}).get(name, {})
    return list(section.get("rows", [])) if section.get("status") == "ok" else []


# -- plots -----------------------------------------------------------------------------------------

def write_plots(result: Mapping[str, Any], out_dir: str | os.PathLike) -> list[Path]:
    """Draw every plot the result has data for into ``out_dir``; return the files written."""
    import matplotlib

    matplotlib.use("Agg")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for key, draw in (("render", _plot_render), ("scaling", _plot_scaling), ("stages", _plot_stages),
                      ("physics", _plot_physics)):
        path = out_dir / PLOT_FILES[key]
        if draw(result, path):
            written.append(path)
    return written


def _save(fig: Any, path: Path) -> bool:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def _plot_render(result: Mapping[str, Any], path: Path) -> bool:
    """One panel per sensor kind: a line per backend (solid in-process, dashed through a worker),
    and the peer's TinyRenderer on the depth panel."""
    import matplotlib.pyplot as plt

    rows = [r for r in _section_rows(result, "render") if "res" in r and r.get("frames_per_s")]
    peer = [r for r in result.get("sections", {}).get("peer", {}).get("depth", []) if r.get("frames_per_s")]
    if not rows and not peer:
        return False
    kinds = sorted({r["kind"] for r in rows} | ({"depth"} if peer else set()), key=lambda k: (k != "depth", k))
    series_name = lambda r: " ".join(  # noqa: E731  raycast rows carry a tracer and a thread count
        str(x) for x in (r["backend"], r.get("tracer"), r.get("threads") and f"x{r['threads']}") if x)
    backends = sorted({series_name(r) for r in rows})
    colours = {b: f"C{i}" for i, b in enumerate(backends)}
    fig, axes = plt.subplots(1, len(kinds), figsize=(4.2 * len(kinds), 4.2), sharey=True, squeeze=False)
    for ax, kind in zip(axes[0], kinds):
        series: dict[tuple[str, str], list[tuple[int, float]]] = {}
        for r in rows:
            if r["kind"] == kind:
                series.setdefault((series_name(r), r.get("where", "")), []).append((int(r["res"]), float(r["frames_per_s"])))
        for (backend, where), pts in sorted(series.items()):
            pts.sort()
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o" + ("--" if where == "worker" else "-"),
                    color=colours[backend], label=f"{backend} ({where.replace('_', '-')})" if where else backend)
        if kind == "depth" and peer:
            pts = sorted((int(r["res"]), float(r["frames_per_s"])) for r in peer)
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "k:s", label="peer: pybullet TinyRenderer")
        ticks = sorted({p[0] for pts in series.values() for p in pts} | ({int(r["res"]) for r in peer} if kind == "depth" else set()))
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xticks(ticks, [f"{t}x{t}" for t in ticks])
        ax.set_title(kind)
        ax.set_xlabel("resolution")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel("frames/s")
    fig.suptitle("Rendering garage-stones: frames/s against resolution")
    return _save(fig, path)


def _plot_scaling(result: Mapping[str, Any], path: Path) -> bool:
    import matplotlib.pyplot as plt

    rows = [r for r in _section_rows(result, "scaling") if r.get("env_steps_per_s")]
    if not rows:
        return False
    fig, ax = plt.subplots(figsize=(6, 4))
    for workers in sorted({r["workers"] for r in rows}):
        pts = sorted((r["scenes"], r["env_steps_per_s"]) for r in rows if r["workers"] == workers)
        ax.plot([p[0] for p in pts], [p[1] for p in pts], "-o", label=f"{workers} worker(s)")
    ax.set_xscale("log", base=2)
    ticks = sorted({r["scenes"] for r in rows})
    ax.set_xticks(ticks, [str(t) for t in ticks])
    ax.set_xlabel("scenes")
    ax.set_ylabel("env-steps/s")
    ax.set_title("VecEnv.step: env-steps/s against scenes and workers")
    ax.set_ylim(bottom=0)
    ax.grid(True, alpha=0.3)
    ax.legend()
    return _save(fig, path)


def _plot_stages(result: Mapping[str, Any], path: Path) -> bool:
    import matplotlib.pyplot as plt

    rows = [r for r in _section_rows(result, "end_to_end") if r.get("stages")]
    if not rows:
        return False
    fig, ax = plt.subplots(figsize=(8, 4.5))
    labels = [f"{r['workers']} worker(s), shm {'on' if r.get('shm') else 'off'}\n{fmt(r.get('env_steps_per_s'))} env-steps/s"
              for r in rows]
    bottom = [0.0] * len(rows)
    for stage in STAGES:
        shares = [100.0 * float(r["stages"].get(stage, 0.0)) for r in rows]
        ax.bar(labels, shares, bottom=bottom, label=stage)
        bottom = [b + s for b, s in zip(bottom, shares)]
    ax.tick_params(axis="x", labelsize=8)
    ax.set_ylabel("share of VecEnv.step wall time (%)")
    ax.set_title("Where a step's time goes")
    ax.set_ylim(0, 100)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    return _save(fig, path)


def _plot_physics(result: Mapping[str, Any], path: Path) -> bool:
    """Simulated drone-seconds per wall second against agents: the one figure comparable with the
    peer, whose steps (240 Hz physics) are not our control steps."""
    import matplotlib.pyplot as plt

    rows = [r for r in _section_rows(result, "physics") if r.get("sim_seconds_per_s")]
    if not rows:
        return False
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    series: dict[str, list[tuple[int, float]]] = {}
    for r in rows:
        label = f"{r.get('mode')}{' + grad' if r.get('grad') else ''}"
        series.setdefault(label, []).append((int(r["agents"]), float(r["sim_seconds_per_s"])))
    for label, pts in sorted(series.items()):
        pts.sort()
        ax.plot([p[0] for p in pts], [p[1] for p in pts], "-o", label=label)
    peer = sorted((p["drones"], p["sim_seconds_per_s"]) for p in result.get("sections", {}).get("peer", {}).get("physics", [])
                  if p.get("sim_seconds_per_s"))
    if peer:
        ax.plot([p[0] for p in peer], [p[1] for p in peer], "k:*", markersize=12, label="peer: pybullet 240 Hz")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("agents")
    ax.set_ylabel("simulated drone-seconds per wall second")
    ax.set_title("Batched dynamics against agents")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)


# -- text and Markdown -----------------------------------------------------------------------------

def ratio_rows(result: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The ratios ours/peer against their goals, as table rows."""
    out = []
    for name, r in result.get("ratios", {}).items():
        out.append({"figure": name, "ours": r.get("ours"), "peer": r.get("peer"), "ratio": r.get("ratio"),
                    "goal": r.get("goal_text", r.get("goal")), "met": r.get("met"), "note": r.get("note", "")})
    return out


def section_text(name: str, section: Mapping[str, Any]) -> str:
    """One section as text: its table, or its error."""
    if section.get("status") != "ok":
        return f"[{name}] {section.get('status', 'missing').upper()}: {section.get('error', 'not run')}"
    if name == "peer":
        parts = []
        if section.get("physics"):
            parts.append(text_table(section["physics"]))
        if section.get("depth"):
            parts.append(text_table(section["depth"]))
        return "\n".join(parts)
    table = text_table(flat_rows(section.get("rows", [])))
    return table + (f"\nnote: {section['note']}" if section.get("note") else "")


def text_report(result: Mapping[str, Any]) -> str:
    """The whole run as plain text for stdout."""
    lines = []
    for name, section in result.get("sections", {}).items():
        lines += [f"== {name} ({fmt(section.get('elapsed_s'))} s)", section_text(name, section), ""]
    lines += ["== ours / peer (pybullet, gym-pybullet-drones style), same machine, same run",
              text_table(ratio_rows(result)), "", f"total: {fmt(result.get('total_s'))} s"]
    return "\n".join(lines)


def markdown_report(result: Mapping[str, Any], md_path: str | os.PathLike, plots_dir: str | os.PathLike) -> str:
    """BENCHMARKS.md: latest figures, machine, command, ratios against goals, plots."""
    m = result.get("machine", {})
    md_dir = Path(md_path).resolve().parent
    lines = [
        "# Benchmarks",
        "",
        "Generated by `visfly-dist bench all` down to the hand-written sections (rerun the command below instead "
        "of editing it; the hand-written part after the mark is kept).",
        "The peer is gym-pybullet-drones' way of simulating (pybullet `DIRECT`, 240 Hz, per-drone force "
        "calls; TinyRenderer camera) on the same scene mesh, measured in the same run on the same machine.",
        "",
        "How to read: an env-step is one agent advanced one control step (a `VecEnv.step` of 100 agents is",
        "100 env-steps). `sim_seconds_per_s` is simulated drone-seconds per wall second (ours:",
        "control steps of 0.02 s, RK4 at 0.005 s; the peer: 240 Hz Bullet steps), compared at the same",
        "number of drones. Stage shares are of `VecEnv.step`'s wall time; `transport` includes",
        "serialisation on both sides. Ratios are ours / peer in the same run.",
        "",
        "## Run",
        "",
        f"- command: `{m.get('command')}`",
        f"- date: {m.get('date')} · commit: `{m.get('git_commit')}`",
        f"- machine: {m.get('cpu_model')}, {m.get('cores')} cores, {m.get('platform')}",
        f"- versions: python {m.get('python')}, torch {m.get('torch')}, numpy {m.get('numpy')}, "
        f"embreex {m.get('embreex')}, pybullet {m.get('pybullet')}",
        f"- preset: {result.get('preset')} · total time: {fmt(result.get('total_s'))} s",
        f"- load average (1/5/15 min) at start {m.get('load_average_start')}, at end {result.get('load_average_end')}",
    ]
    if result.get("busy_note"):
        lines.append(f"- **note:** {result['busy_note']}")
    lines += ["", "## Goals", "", markdown_table(ratio_rows(result)), ""]
    titles = {"physics": "Physics (batched dynamics)", "render": "Rendering and obstacle queries",
              "end_to_end": "End to end: VecEnv.step", "scaling": "Scaling: scenes and workers",
              "peer": "Peer: pybullet"}
    for name, section in result.get("sections", {}).items():
        lines += [f"## {titles.get(name, name)}", ""]
        if section.get("status") != "ok":
            lines += [f"**{section.get('status', 'missing')}:** `{section.get('error', 'not run')}`", ""]
            continue
        if name == "peer":
            if section.get("physics"):
                lines += [markdown_table(section["physics"]), ""]
            if section.get("depth"):
                lines += [markdown_table(section["depth"]), ""]
        else:
            lines += [markdown_table(flat_rows(section.get("rows", []))), ""]
        if section.get("note"):
            lines += [section["note"], ""]
    plots = [(key, Path(plots_dir) / f) for key, f in PLOT_FILES.items() if (Path(plots_dir) / f).exists()]
    if plots:
        lines += ["## Plots", ""]
        for key, p in plots:
            rel = os.path.relpath(p.resolve(), md_dir)
            lines += [f"![{key}]({rel})", ""]
    return "\n".join(lines)


HAND_WRITTEN_MARK = "<!-- Hand-written sections below: `visfly-dist bench all --md` keeps everything after this line. -->"
"""In an existing report, this line and what follows it (before/after studies written by hand) survive a rewrite."""


def write_markdown(result: Mapping[str, Any], md_path: str | os.PathLike, plots_dir: str | os.PathLike) -> Path:
    """Write the report; an existing file's hand-written part (from :data:`HAND_WRITTEN_MARK` on) is kept."""
    path = Path(md_path)
    path.parent.mkdir(parents=True, exist_ok=True)
    kept = ""
    if path.exists():
        old = path.read_text()
        at = old.find(HAND_WRITTEN_MARK)
        if at >= 0:
            kept = "\n" + old[at:]
    path.write_text(markdown_report(result, path, plots_dir).rstrip("\n") + "\n" + kept)
    return path
