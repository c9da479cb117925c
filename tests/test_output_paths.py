"""Commands check their output paths and numeric options before their work (one line, exit 2), and
write where they say they wrote."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from visfly_dist.cli import main
from visfly_dist.errors import ConfigError
from visfly_dist.output_paths import check_output_dir, check_output_file


def test_a_writable_file_path_is_checked_without_leaving_a_file(tmp_path: Path) -> None:
    out = check_output_file(tmp_path / "new" / "rows.json", "--json")
    assert out.parent.is_dir() and not out.exists()
    kept = tmp_path / "kept.json"
    kept.write_text("old")
    check_output_file(kept, "--json")
    assert kept.read_text() == "old"  # appended to nothing, not truncated


@pytest.mark.parametrize("name, suffixes, message", [
    ("", (), "--json is empty"),
    ("a_folder", (), "is a folder; give a file name"),
    ("film.mp4", (".gif",), "must end in .gif"),
    ("a_file/under", (), "cannot be written: a folder on its path is a file"),
])
def test_an_unwritable_file_path_is_named(tmp_path: Path, name: str, suffixes: tuple[str, ...], message: str) -> None:
    (tmp_path / "a_folder").mkdir()
    (tmp_path / "a_file").write_text("x")
    with pytest.raises(ConfigError, match=message):
        check_output_file(str(tmp_path / name) if name else "", "--json", suffixes)


def test_a_folder_path_must_be_a_writable_folder(tmp_path: Path) -> None:
    assert check_output_dir(tmp_path / "made" / "here", "--out").is_dir()
    (tmp_path / "a_file").write_text("x")
    with pytest.raises(ConfigError, match="is a file, not a folder"):
        check_output_dir(tmp_path / "a_file", "--out")
    with pytest.raises(ConfigError, match="cannot be written"):
        check_output_dir("/proc/visfly_nope", "--out")


@pytest.mark.parametrize("argv, message", [
    (["scenes", "generate", "empty", "--out", "{file}"], "--out '{file}' is a file, not a folder"),
    (["scenes", "generate", "garage-stones", "--param", "start_center=100,0,1", "--out", "{tmp}/s"],
     r"start_center \(100.0, 0.0, 1.0\) ± start_half .* must lie inside the garage"),
    (["plot", "step-response", "--out", "{tmp}/p", "--duration", "-1"], r"--duration -1.0 must be in \(0, 600\]"),
    (["plot", "step-response", "--out", "{tmp}/p", "--duration", "nan"], "--duration nan must be in"),
    (["plot", "step-response", "--out", "{file}"], "is a file, not a folder"),
    (["bench", "physics", "--agents", "10", "--steps", "0", "--no-compile"], r"steps=0 .* must be >= 1"),
    (["bench", "physics", "--agents", "10", "--threads", "0", "--no-compile"], "--threads 0 must be >= 1"),
    (["bench", "physics", "--agents", "10", "--modes", "compiled", "--no-compile"], "which --no-compile skips"),
    (["bench", "physics", "--agents", "10", "--no-compile", "--json", "/proc/x.json"], "--json '/proc/x.json' cannot be written"),
    (["bench", "step", "--agents", "2", "--workers", "0"], "--workers 0 must be >= 1"),
    (["bench", "step", "--agents", "2", "--steps", "0"], "--steps 0 must be >= 1"),
    (["bench", "render", "--quick", "--no-worker", "--moving", "-1", "--res", "16", "--agents", "2"],
     r"moving=-1 must be in \[0, 100\]"),
    (["eval", "hover", "--checkpoint", "{tmp}/final.zip", "--video", "{tmp}/film.mp4"], "--video .* must end in .gif"),
    (["eval", "hover", "--checkpoint", "{tmp}/final.zip", "--json", "{tmp}"], "--json .* is a folder"),
    (["eval", "hover", "--checkpoint", "{tmp}/final.zip", "--num-envs", "0"], "--num-envs 0 must be >= 1"),
    (["eval", "hover", "--checkpoint", "{tmp}/config.json"], "is not a checkpoint; pass a .zip"),
])
def test_a_bad_output_or_count_fails_before_any_work(argv: list[str], message: str, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    afile = tmp_path / "afile"
    afile.write_text("x")
    for name in ("final.zip", "config.json"):
        (tmp_path / name).write_bytes(b"")  # never read: the options are checked first
    fill = {"tmp": str(tmp_path), "file": str(afile)}
    assert main([a.format(**fill) for a in argv]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1, captured.err
    assert re.search(message.format(**fill), err[0]), err[0]
    assert "wrote" not in captured.out and "[bench" not in captured.out


@pytest.mark.skipif(torch.cuda.is_available(), reason="this host has a GPU torch can use")
def test_bench_physics_on_cuda_without_a_gpu_names_torchs_build(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "physics", "--agents", "10", "--no-compile", "--device", "cuda"]) == 2
    assert "--device cuda: torch" in capsys.readouterr().err


def test_scene_generation_replaces_an_older_scene_and_preview_writes_the_file_it_names(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "scene"
    assert main(["scenes", "generate", "pillars", "--seed", "1", "--out", str(out)]) == 0
    assert len(list((out / "objects").iterdir())) > 2
    assert main(["scenes", "generate", "empty", "--out", str(out)]) == 0
    import json
    listed = {o["mesh"] for o in json.loads((out / "scene.json").read_text())["objects"]}
    assert {f"objects/{p.name}" for p in (out / "objects").iterdir()} == listed  # the pillars' meshes are gone
    capsys.readouterr()
    assert main(["scenes", "preview", str(out), "--out", str(tmp_path / "noext")]) == 2
    assert "must end in .png or .jpg or .jpeg" in capsys.readouterr().err
    assert main(["scenes", "preview", str(out), "--out", str(tmp_path / "view.png")]) == 0
    assert (tmp_path / "view.png").stat().st_size > 0 and str(tmp_path / "view.png") in capsys.readouterr().out
