"""Key expressions and session configuration."""

from __future__ import annotations

import json

import pytest

from visfly_dist.errors import ConfigError
from visfly_dist.protocol import keys
from visfly_dist.protocol.session import SessionConfig, client_of


def test_keys_are_namespaced_by_run_and_worker():
    assert keys.worker_rpc("run-1", "host.a-7") == "visfly/run-1/worker/host.a-7/rpc"
    assert keys.worker_alive("run-1", "w0") == "visfly/run-1/alive/worker/w0"
    assert keys.workers_alive_pattern("run-1") == "visfly/run-1/alive/worker/*"
    assert keys.worker_id_from_alive_key(keys.worker_alive("r", "w9")) == "w9"


@pytest.mark.parametrize("bad", ["", "a/b", "*", "**", "a b", "x?y", "a#b", "$*", None, "r1\n", "\nr1", "r" * 257])
def test_keys_refuse_unsafe_chunks(bad):
    with pytest.raises(ConfigError, match="must be a non-empty string of at most 256 letters"):
        keys.worker_rpc("run", bad)
    with pytest.raises(ConfigError, match="run_id="):
        keys.worker_alive(bad, "w")


def test_session_config_builds_the_zenoh_config():
    cfg = SessionConfig(mode="peer", listen=("tcp/127.0.0.1:7451",), shared_memory=False, lease_ms=500).to_zenoh()
    assert json.loads(cfg.get_json("mode")) == "peer"
    assert json.loads(cfg.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7451"]
    assert json.loads(cfg.get_json("transport/shared_memory/enabled")) is False
    assert json.loads(cfg.get_json("transport/link/tx/lease")) == 500
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    client = client_of(["tcp/127.0.0.1:7451"])
    assert (client.mode, client.listen, client.shared_memory) == ("client", (), True)


@pytest.mark.parametrize("kwargs, match", [
    ({"mode": "server"}, "mode='server' must be one of"),
    ({"connect": ("localhost:7447",)}, "endpoint 'localhost:7447' must look like"),
    ({"lease_ms": 10}, "lease_ms=10 must be in"),
])
def test_session_config_refuses_bad_values(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        SessionConfig(**kwargs)
