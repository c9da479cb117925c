"""A preview sheet of a scene: RGB, depth and segmentation from a few cameras, and a top-down map.

The views are drawn by the worker's own renderers (``make_renderer``), so the sheet shows what the
drones would see. Viewpoints: the start region's centre looking at the goal (or the pad, or the
scene centre) when the metadata has them, then two high corners of the bounds looking at the centre.
The map draws every triangle below the ceiling from above (higher triangles on top) with the
scene's regions and the viewpoints marked.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.scene_worker.render_base import face_rgb, make_renderer
from visfly_dist.scenes.scene import Scene


def preview_scene(scene: Scene, out: Path, backend: str = "raycast", width: int = 192, height: int = 144) -> Path:
    """Render the preview sheet of ``scene`` to the PNG ``out`` and return its path.

    Args:
        scene: the scene to show.
        out: PNG file to write (parent directories are created).
        backend: ``"raycast"``, ``"egl"`` or ``"auto"``.
        width, height: size of each rendered view in pixels.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    eyes, poses = viewpoints(scene)
    far = float(np.linalg.norm(scene.bounds[1] - scene.bounds[0])) + 1.0
    cameras = [CameraSpec(name=kind, kind=kind, width=width, height=height, hfov_deg=90.0, far=far)
               for kind in ("rgb", "depth", "segmentation")]
    with make_renderer(backend, scene, cameras) as renderer:
        images = renderer.render(poses)

    rows = len(poses)
    fig = plt.figure(figsize=(16, 3.2 * rows + 0.6))
    try:
        return _draw_sheet(fig, scene, eyes, images, renderer.name, far, Path(out))
    finally:
        plt.close(fig)


def _draw_sheet(fig, scene: Scene, eyes: np.ndarray, images: dict, backend: str, far: float, out: Path) -> Path:
    rows = len(eyes)
    grid = fig.add_gridspec(rows, 4, width_ratios=[1, 1, 1, 1.6])
    for row in range(rows):
        rgb_ax, depth_ax, seg_ax = (fig.add_subplot(grid[row, col]) for col in range(3))
        rgb_ax.imshow(np.moveaxis(images["rgb"][row], 0, -1))
        shown = depth_ax.imshow(images["depth"][row, 0], cmap="viridis", vmin=0.0, vmax=far)
        fig.colorbar(shown, ax=depth_ax, fraction=0.046, pad=0.02, label="depth (m)")
        seg_ax.imshow(_segmentation_rgb(images["segmentation"][row, 0]), interpolation="nearest")
        rgb_ax.set_ylabel(f"view {row + 1}")
        for ax in (rgb_ax, depth_ax, seg_ax):
            ax.set_xticks([])
            ax.set_yticks([])
        if row == 0:
            rgb_ax.set_title(f"RGB ({backend})")
            depth_ax.set_title("depth")
            seg_ax.set_title("segmentation")
    _top_down_map(fig.add_subplot(grid[:, 3]), scene, eyes)
    fig.suptitle(f"{scene.name}: {len(scene.objects)} objects, {scene.num_triangles} triangles")
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80, bbox_inches="tight")
    return out


def viewpoints(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Camera positions ``(k, 3)`` and drone poses ``(k, 7)`` for the preview's views."""
    low, high = scene.bounds
    center = (low + high) / 2
    meta = scene.metadata
    target = next((np.asarray(meta[k], dtype=np.float64) for k in ("goal", "pad_center") if k in meta), center)
    points = []
    if "start_region" in meta:
        points.append(np.mean(np.asarray(meta["start_region"], dtype=np.float64), axis=0))
    inset = 0.08 * (high - low)
    points.append(np.array([low[0] + inset[0], low[1] + inset[1], high[2] - inset[2]]))
    points.append(np.array([high[0] - inset[0], high[1] - inset[1], high[2] - inset[2]]))
    eyes = np.array(points)
    targets = np.array([target] + [center] * (len(eyes) - 1)) if "start_region" in meta else np.tile(center, (len(eyes), 1))
    poses = np.array([np.concatenate([eye, look_at_quaternion(eye, aim)]) for eye, aim in zip(eyes, targets)])
    return eyes, poses


def look_at_quaternion(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Quaternion wxyz turning body +x from ``eye`` towards ``target`` (yaw, then pitch; no roll)."""
    d = np.asarray(target, dtype=np.float64) - np.asarray(eye, dtype=np.float64)
    yaw = math.atan2(d[1], d[0])
    pitch = -math.atan2(d[2], math.hypot(d[0], d[1]))  # positive pitch tips the nose down (FLU)
    cy, sy, cp, sp = math.cos(yaw / 2), math.sin(yaw / 2), math.cos(pitch / 2), math.sin(pitch / 2)
    return np.array([cy * cp, -sy * sp, cy * sp, sy * cp])


def _segmentation_rgb(ids: np.ndarray) -> np.ndarray:
    """Distinct colours per object id (a fixed hash), black for 0."""
    import matplotlib
    from matplotlib.colors import ListedColormap

    tab20 = matplotlib.colormaps["tab20"]
    assert isinstance(tab20, ListedColormap)  # a list of 20 colours
    palette = (np.asarray(tab20.colors) * 255).astype(np.uint8)
    rgb = palette[(ids.astype(np.int64) * 7) % len(palette)]
    rgb[ids == 0] = 0
    return rgb


def _top_down_map(ax, scene: Scene, eyes: np.ndarray) -> None:
    from matplotlib.collections import PolyCollection
    from matplotlib.patches import Rectangle

    low, high = scene.bounds
    polygons, colors, heights = [], [], []
    for obj in scene.at_time(0.0).objects:   # moving obstacles where they are at t = 0 (as rendered)
        mesh = obj.mesh
        triangles = mesh.triangles
        below_ceiling = triangles[:, :, 2].min(axis=1) < high[2] - 1e-3
        face_colors = face_rgb(mesh)
        polygons.append(triangles[below_ceiling, :, :2])
        colors.append(face_colors[below_ceiling])
        heights.append(triangles[below_ceiling, :, 2].max(axis=1))
    order = np.argsort(np.concatenate(heights), kind="stable")
    # a 3-D array of polygons is PolyCollection's fast path (its stubs say a sequence of them)
    ax.add_collection(PolyCollection(np.concatenate(polygons)[order],  # type: ignore[arg-type]
                                     facecolors=np.concatenate(colors)[order] / 255.0,
                                     edgecolors="none"))
    ax.add_patch(Rectangle(low[:2], *(high - low)[:2], fill=False, edgecolor="black", linestyle="--", label="bounds"))
    meta = scene.metadata
    for key, color in (("start_region", "tab:green"), ("goal_region", "tab:red")):
        if key in meta:
            region = np.asarray(meta[key], dtype=np.float64)
            ax.add_patch(Rectangle((region[0, 0], region[0, 1]), *(region[1] - region[0])[:2], fill=False, edgecolor=color,
                                   lw=2, label=key))
    for key, marker in (("goal", "*"), ("pad_center", "s"), ("gap_center", "D")):
        if key in meta:
            ax.plot(*np.asarray(meta[key])[:2], marker, color="tab:red", ms=12, label=key)
    if "targets" in meta:
        ax.plot(*np.asarray(meta["targets"])[:, :2].T, "x", color="tab:red", ms=10, label="targets")
    for k, motion in enumerate(o.motion for o in scene.objects if o.motion is not None):   # their paths, dotted
        path = motion.position(np.linspace(0.0, motion.period, 201))[:, :2]
        ax.plot(*path.T, ":", color="tab:orange", lw=1,
                label="moving obstacle paths" if k == 0 else None)
    for i, eye in enumerate(eyes):
        ax.annotate(f"{i + 1}", eye[:2], color="white", ha="center", va="center",
                    bbox={"boxstyle": "circle", "fc": "tab:blue"})
    ax.set_xlim(low[0] - 0.5, high[0] + 0.5)
    ax.set_ylim(low[1] - 0.5, high[1] + 0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("top-down (ceiling hidden)")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=3, fontsize=8)

