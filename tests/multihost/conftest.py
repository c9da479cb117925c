"""Fixtures of the multi-host tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.multihost.deployed import copy_deploy_configs


@pytest.fixture
def deploy_configs(tmp_path: Path):
    """``deploy_configs(router_host)``: a copy of ``deploy/zenoh`` with certificates for ``router_host``."""
    return lambda router_host: copy_deploy_configs(tmp_path / f"zenoh-{router_host}", router_host)
