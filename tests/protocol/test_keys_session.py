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


def _write(path, text: str) -> str:
    path.write_text(text)
    return str(path)


def test_a_config_file_sits_under_our_own_settings(tmp_path):
    (tmp_path / "certs").mkdir()
    (tmp_path / "certs" / "ca.pem").write_text("not checked here")
    path = _write(tmp_path / "z.json5", """// comments are fine
        { mode: "router", listen: { endpoints: ["tcp/0.0.0.0:9"] }, transport: {
          link: { tx: { lease: 9999 }, tls: { root_ca_certificate: "certs/ca.pem" } },
          auth: { usrpwd: { user: "trainer", password: "pw" } } } }""")
    config = SessionConfig(mode="client", connect=("tcp/127.0.0.1:7451",), listen=(), lease_ms=700, config_file=path)
    cfg = config.to_zenoh()
    assert json.loads(cfg.get_json("mode")) == "client"  # ours win
    assert json.loads(cfg.get_json("listen/endpoints")) == []
    assert json.loads(cfg.get_json("transport/link/tx/lease")) == 700
    # the rest of the file is used, with paths relative to the file's folder
    assert json.loads(cfg.get_json("transport/link/tls/root_ca_certificate")) == str(tmp_path / "certs" / "ca.pem")
    assert config.user() == "trainer"


def test_zenoh_config_variable_is_used_when_no_file_is_given(tmp_path, monkeypatch):
    path = _write(tmp_path / "env.json5", '{transport: {auth: {usrpwd: {user: "worker", password: "pw"}}}}')
    monkeypatch.setenv("ZENOH_CONFIG", path)
    assert SessionConfig().config_file == path
    assert client_of(["tcp/127.0.0.1:7451"]).user() == "worker"
    other = _write(tmp_path / "flag.json5", "{}")
    assert SessionConfig(config_file=other).config_file == other  # an explicit file wins
    monkeypatch.delenv("ZENOH_CONFIG")
    assert SessionConfig().config_file is None and SessionConfig().user() is None


@pytest.mark.parametrize("text, match", [
    (None, "zenoh config file '.*missing.json5' does not exist"),
    ("{ mode: 'client', ", "zenoh config file '.*bad.json5' is not a valid Zenoh config: .*expected"),
    ("{ transport: { nope: 1 } }", "zenoh config file '.*bad.json5' is not a valid Zenoh config: .*unknown field `nope`"),
    ("{ transport: { link: { tls: { root_ca_certificate: 'certs/none.pem' } } } }",
     "zenoh config file '.*bad.json5': transport/link/tls/root_ca_certificate 'certs/none.pem' does not exist"),
])
def test_a_bad_config_file_is_named_in_the_error(tmp_path, monkeypatch, text, match):
    path = str(tmp_path / "missing.json5") if text is None else _write(tmp_path / "bad.json5", text)
    with pytest.raises(ConfigError, match=match):
        SessionConfig(config_file=path)
    monkeypatch.setenv("ZENOH_CONFIG", path)
    with pytest.raises(ConfigError, match=match):
        SessionConfig()
