"""``visfly-dist scenes generate|preview`` run as the user runs them (subprocesses)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from visfly_dist.scenes import generate_scene, load_scene

REPO = Path(__file__).resolve().parents[2]


def run_cli(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    return subprocess.run([sys.executable, "-m", "visfly_dist.cli", "scenes", *args],
                          capture_output=True, text=True, timeout=120, env=env, cwd=REPO)


def test_generate_then_preview(tmp_path):
    out = tmp_path / "garage"
    done = run_cli("generate", "garage-stones", "--seed", "4", "--out", str(out),
                   "--param", "density=0.05", "--param", "goal_center=10,1,1.5")
    assert done.returncode == 0, done.stderr
    assert "wrote gen:garage-stones?seed=4" in done.stdout
    scene = load_scene(out)
    expected = generate_scene("garage-stones", seed=4, density=0.05, goal_center=(10, 1, 1.5))
    assert scene.name == expected.name and scene.metadata["goal"] == [10.0, 1.0, 1.5]
    np.testing.assert_array_equal(scene.objects[-1].mesh.vertices, expected.objects[-1].mesh.vertices)

    png = tmp_path / "sheet.png"
    done = run_cli("preview", str(out), "--out", str(png), "--backend", "raycast")
    assert done.returncode == 0, done.stderr
    image = iio.imread(png)
    assert image.ndim == 3 and image.shape[0] > 300 and image.shape[1] > 600
    assert len(np.unique(image.reshape(-1, image.shape[2])[:, :3], axis=0)) > 100  # views drawn, not blank


@pytest.mark.parametrize("backend", ["raycast", "egl"])
def test_preview_of_a_gen_spec(tmp_path, backend):
    png = tmp_path / "pad.png"
    done = run_cli("preview", "gen:landing-pad?seed=0&pad_size=1.0", "--out", str(png), "--backend", backend)
    assert done.returncode == 0, done.stderr
    assert f"wrote preview of gen:landing-pad?seed=0&pad_size=1.0 to {png}" in done.stdout
    assert png.stat().st_size > 10_000


def test_user_errors_exit_2_with_one_line(tmp_path):
    done = run_cli("generate", "volcano", "--out", str(tmp_path / "x"))
    assert done.returncode == 2
    assert "unknown scene kind 'volcano'; valid kinds:" in done.stderr and "Traceback" not in done.stderr
    done = run_cli("generate", "empty", "--out", str(tmp_path / "x"), "--param", "density")
    assert done.returncode == 2 and "--param 'density' must look like key=value" in done.stderr


@pytest.mark.parametrize("backend", ["raycast", "egl"])
def test_preview_of_a_textured_glb_with_up_option(tmp_path, backend):
    from tests.scene_worker.test_shading import textured_quad

    floor = textured_quad()
    floor.apply_translation([-3.0, 0.0, 0.0])
    floor.export(tmp_path / "wall.glb")
    png = tmp_path / "wall.png"
    done = run_cli("preview", f"{tmp_path / 'wall.glb'}?up=z", "--out", str(png), "--backend", backend)
    assert done.returncode == 0, done.stderr
    assert png.stat().st_size > 10_000


def test_every_preview_failure_is_one_line_and_exit_code_2(tmp_path):
    (tmp_path / "a_directory.png").mkdir()
    trimesh_box = tmp_path / "box.stl"
    import trimesh

    trimesh.creation.box().export(trimesh_box)
    failures = {
        "missing": ("preview", str(tmp_path / "missing.glb"), "--out", str(tmp_path / "x.png")),
        "bad option": ("preview", f"{trimesh_box}?up=q", "--out", str(tmp_path / "x.png")),
        "unwritable out": ("preview", str(trimesh_box), "--out", str(tmp_path / "a_directory.png")),
        "garbage mesh": ("preview", str(tmp_path / "junk.glb"), "--out", str(tmp_path / "x.png")),
    }
    (tmp_path / "junk.glb").write_bytes(b"not a glb at all")
    for what, args in failures.items():
        done = run_cli(*args)
        assert done.returncode == 2, (what, done.stderr)
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("visfly-dist scenes preview: error: "), (what, done.stderr)
