"""The checked rules (docs/ARCHITECTURE.md "Imports"): import contracts, lint and types.

- ``lint-imports`` checks the contracts in pyproject.toml ``[tool.importlinter]``: the layers
  (imports point one way), the forbidden imports (the worker never imports the aggregator or torch,
  the dynamics nothing of ours but errors and host, a task never talks to Zenoh, the env side reaches
  the workers only through the protocol) and no import cycles between sibling modules or packages.
  Every import statement counts, lazy ones inside functions included.
- ``visfly_dist.host`` imports the standard library only.
- ``ruff check visfly_dist`` and ``mypy visfly_dist`` pass with the configuration in pyproject.toml.

The tools come with the ``dev`` extra (``pip install -e .[dev]``; test.sh installs it).
"""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _run(*command: str, timeout: float = 600) -> None:
    """Run a checker in the repository root; fail with its whole output unless it exits 0."""
    exe = shutil.which(command[0]) or shutil.which(command[0], path=str(Path(sys.executable).parent))
    if exe is None:
        pytest.fail(f"{command[0]} is not installed: pip install -e '.[dev]' (test.sh does)")
    proc = subprocess.run([exe, *command[1:]], cwd=REPO, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        pytest.fail(f"{' '.join(command)} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}", pytrace=False)


def test_import_contracts_hold() -> None:
    _run("lint-imports", "--no-cache")


def test_host_imports_only_the_standard_library() -> None:
    tree = ast.parse((REPO / "visfly_dist" / "host.py").read_text())
    imported = {alias.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
    imported |= {node.module.split(".")[0] for node in ast.walk(tree)
                 if isinstance(node, ast.ImportFrom) and node.module and not node.level}
    assert not any(isinstance(node, ast.ImportFrom) and node.level for node in ast.walk(tree))
    outside = sorted(m for m in imported if m not in sys.stdlib_module_names and m != "__future__")
    assert not outside, f"visfly_dist/host.py must import the standard library only; it imports {outside}"


def test_ruff_is_clean() -> None:
    _run("ruff", "check", "visfly_dist")


def test_mypy_is_clean() -> None:
    _run("mypy", "visfly_dist")
