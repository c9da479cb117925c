"""Checks that a command's output file or folder can be written, made before the work that fills it.

An evaluation, a benchmark or a generated scene that runs for minutes and then fails on its
``--json`` / ``--video`` / ``--out`` path loses its result; each command checks its paths first, so
a bad one is a one-line ``ConfigError`` naming the flag. The check writes for real (makes the
folder, opens the file for appending, removes a file it created): permission bits do not tell a
root user that ``/proc`` cannot hold a file.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Sequence

from visfly_dist.errors import ConfigError


def check_output_file(path: str | Path, flag: str, suffixes: Sequence[str] = ()) -> Path:
    """``path`` as a Path, once a file can be written there (its folder is made); ``suffixes``: the
    endings accepted (lower case, with the dot), any when empty.

    Raises:
        ConfigError: naming ``flag``: empty, a folder, another ending, or not writable.
    """
    if not str(path).strip():
        raise ConfigError(f"{flag} is empty; give a file name")
    out = Path(path)
    if suffixes and out.suffix.lower() not in suffixes:
        raise ConfigError(f"{flag} {str(out)!r} must end in {' or '.join(suffixes)}")
    if out.is_dir():
        raise ConfigError(f"{flag} {str(out)!r} is a folder; give a file name")
    existed = out.exists()
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with open(out, "ab"):
            pass
    except (FileExistsError, NotADirectoryError):
        raise ConfigError(f"{flag} {str(out)!r} cannot be written: a folder on its path is a file") from None
    except OSError as exc:
        raise ConfigError(f"{flag} {str(out)!r} cannot be written: {exc.strerror or exc}") from None
    if not existed:
        out.unlink(missing_ok=True)
    return out


def check_output_dir(path: str | Path, flag: str) -> Path:
    """``path`` as a Path, once it is a folder files can be written into (made if missing).

    Raises:
        ConfigError: naming ``flag``: empty, a file, or not writable.
    """
    if not str(path).strip():
        raise ConfigError(f"{flag} is empty; give a folder")
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=out).close()
    except FileExistsError:
        raise ConfigError(f"{flag} {str(out)!r} is a file, not a folder") from None
    except OSError as exc:
        raise ConfigError(f"{flag} {str(out)!r} cannot be written: {exc.strerror or exc}") from None
    return out
