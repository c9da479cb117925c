"""``visfly-dist scenes``: generate a scene to disk, or draw a preview sheet of one.

    visfly-dist scenes generate garage-stones --seed 3 --out scenes/garage3 --param density=0.2
    visfly-dist scenes preview scenes/garage3 --out garage3.png --backend raycast
    visfly-dist scenes preview "gen:gap-walls?seed=0&gap_width=1.0" --out gap.png

Heavy imports (trimesh, renderers, matplotlib) happen inside the commands, so ``--help`` stays fast.
The command lives in ``scene_worker`` because ``preview`` draws with the worker's renderers:
``scene_worker -> scenes`` is the allowed direction, and ``scenes`` imports nothing of the worker.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from visfly_dist.errors import SceneError
from visfly_dist.output_paths import check_output_dir, check_output_file

KINDS = ("garage-stones", "gap-walls", "landing-pad", "pillars", "empty")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="scenes_command", metavar="ACTION", required=True)

    gen = sub.add_parser("generate", help="write a generated scene directory (scene.json + meshes)")
    gen.add_argument("kind", help=f"generator: {', '.join(KINDS)}")
    gen.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    gen.add_argument("--out", required=True, type=Path, help="output directory")
    gen.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                     help="generator param, e.g. density=0.2 or start_center=1,0,1.5 (repeatable)")
    gen.set_defaults(func=generate)

    preview = sub.add_parser("preview", help="draw RGB/depth/segmentation views and a top-down map to a PNG")
    preview.add_argument("scene", help="scene path (directory, scene.json, mesh[?up=y|z], *.scene_instance.json) or gen: spec")
    preview.add_argument("--out", required=True, type=Path, help="PNG file to write")
    preview.add_argument("--backend", choices=("raycast", "egl"), default="raycast", help="renderer (default raycast)")
    preview.set_defaults(func=preview_command)


PREVIEW_SUFFIXES = (".png", ".jpg", ".jpeg")


def generate(args: argparse.Namespace) -> int:
    from visfly_dist.scenes.generators import generate_scene, parse_value
    from visfly_dist.scenes.storage import save_scene

    params = {}
    for item in args.param:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise SceneError(f"--param {item!r} must look like key=value, e.g. density=0.2")
        params[key] = parse_value(value)
    check_output_dir(args.out, "--out")
    scene = generate_scene(args.kind, args.seed, **params)
    out = save_scene(scene, args.out)
    print(f"wrote {scene.name} ({len(scene.objects)} objects, {scene.num_triangles} triangles) to {out}")
    return 0


def preview_command(args: argparse.Namespace) -> int:
    """Draw the preview sheet; every failure is reported as one line on stderr with exit code 2."""
    from visfly_dist.errors import VisflyError

    try:
        return _preview(args)
    except Exception as exc:  # noqa: BLE001 - the CLI boundary: any failure becomes one line, exit 2
        message = " ".join(str(exc).split()) or "no details"
        cause = "" if isinstance(exc, VisflyError) else f"{type(exc).__name__}: "
        print(f"visfly-dist scenes preview: error: {cause}{message}", file=sys.stderr)
        return 2


def _preview(args: argparse.Namespace) -> int:
    from visfly_dist.scene_worker.preview import preview_scene
    from visfly_dist.scenes.source_syntax import GEN_PREFIX, split_path_source
    from visfly_dist.scenes.sources import resolve_source
    from visfly_dist.scenes.storage import load_scene

    check_output_file(args.out, "--out", PREVIEW_SUFFIXES)  # the name printed is the file written
    if args.scene.startswith(GEN_PREFIX):
        scene = resolve_source(args.scene, roots=[])
    else:
        path, options = split_path_source(args.scene)
        scene = load_scene(path, up_axis=options.get("up"))
    out = preview_scene(scene, args.out, backend=args.backend)
    print(f"wrote preview of {scene.name} to {out}")
    return 0
