"""The cluster files in ``deploy/``: Kubernetes manifests against their schema, container commands
against the command line they run."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from visfly_dist.cli import build_parser

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
MANIFESTS = sorted((DEPLOY / "k8s").glob("*.yaml"))


def _documents(path: Path) -> list[dict]:
    return [d for d in yaml.safe_load_all(path.read_text()) if d]


def _container_commands() -> list[list[str]]:
    commands = []
    for path in MANIFESTS:
        for doc in _documents(path):
            for c in doc.get("spec", {}).get("template", {}).get("spec", {}).get("containers", []):
                commands.append(list(c["args"]))
    compose = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
    commands += [list(s["command"]) for s in compose["services"].values()]
    return commands


@pytest.mark.parametrize("path", MANIFESTS, ids=lambda p: p.name)
def test_kubernetes_manifests_match_the_schema(path):
    kv = pytest.importorskip("kubernetes_validate", reason="kubernetes-validate (PyPI) is not installed")
    for doc in _documents(path):
        kv.validate(doc, kv.latest_version(), strict=True)  # raises ValidationError


@pytest.mark.parametrize("argv", _container_commands(), ids=lambda a: a[0])
def test_container_commands_are_valid_command_lines(argv):
    args = build_parser(only=argv[0]).parse_args(argv)
    assert args.func is not None
