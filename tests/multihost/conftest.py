"""Fixtures of the multi-host tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.multihost.deployed import copy_deploy_configs


@pytest.fixture
def deploy_configs(tmp_path: Path):
    """``deploy_configs(router_host)``: a copy of ``deploy/zenoh`` with certificates for ``router_host``."""
    return lambda router_host: copy_deploy_configs(tmp_path / f"zenoh-{router_host}", router_host)


@pytest.fixture(autouse=True)
def _no_zenoh_config_from_the_caller(monkeypatch):
    """These tests choose every config themselves; a ZENOH_CONFIG in the caller's shell must not leak in."""
    monkeypatch.delenv("ZENOH_CONFIG", raising=False)
