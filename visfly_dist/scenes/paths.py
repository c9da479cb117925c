"""Confining scene file paths to configured roots.

A worker only reads files under its ``--scene-root`` directories. Paths are resolved (``..`` and
symlinks followed) before the check, so neither ``../../etc/passwd`` nor a symlink pointing out of a
root gets through.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Sequence

from visfly_dist.errors import SceneError

PathLike = str | os.PathLike


def normalize_roots(roots: Iterable[PathLike] | None) -> list[Path] | None:
    """Resolved root directories, or None (no confinement) when ``roots`` is None."""
    if roots is None:
        return None
    return [Path(r).expanduser().resolve() for r in roots]


def is_inside(path: Path, roots: Sequence[Path]) -> bool:
    """Whether the resolved ``path`` lies in (or is) one of the resolved ``roots``."""
    resolved = path.resolve()
    return any(resolved == root or resolved.is_relative_to(root) for root in roots)


def check_inside(path: PathLike, roots: Sequence[Path] | None, what: str = "scene file") -> Path:
    """Return ``path`` resolved, raising SceneError when it falls outside every root.

    Args:
        path: the file about to be read.
        roots: resolved roots (from :func:`normalize_roots`); None disables the check.
        what: how to name the file in the error.
    """
    resolved = Path(path).resolve()
    if roots is not None and not is_inside(resolved, roots):
        raise SceneError(
            f"{what} {str(path)!r} resolves to {str(resolved)!r}, outside the scene roots "
            f"{[str(r) for r in roots]}; place it under a root or add its directory as a root"
        )
    return resolved
