"""The shipped Zenoh configs against real routers on loopback: typed refusals and an ACL that denies.

Routers are ``visfly-dist router`` processes started with the files from ``deploy/zenoh`` (copied
with fresh certificates); workers are ``visfly-dist worker`` processes.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest
import zenoh

from tests.aggregator.conftest import make_aggregator
from tests.helpers import REPO, _read_line, call, free_port, start_worker, stop_process, wait_for
from tests.multihost.deployed import copy_deploy_configs
from visfly_dist.errors import AccessDeniedError, AuthenticationError, RouterUnreachableError, TlsHandshakeError
from visfly_dist.protocol import keys
from visfly_dist.protocol.messages import Health
from visfly_dist.protocol.session import client_of, open_session

RUN = "exp1"  # the run id deploy/zenoh/router-acl.json5 allows


def _router(config, endpoint: str) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "visfly_dist.cli", "router", "--listen", endpoint,
                             "--zenoh-config", str(config)], cwd=REPO, stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    line = _read_line(proc, 30.0)
    if "router ready" not in line:
        stop_process(proc)
        pytest.fail(f"router did not start: {line!r} {proc.stderr.read().decode()}")
    return proc


@pytest.fixture(scope="module")
def configs(tmp_path_factory):
    out = copy_deploy_configs(tmp_path_factory.mktemp("zenoh"), "127.0.0.1")
    (out / "wrong-password.json5").write_text(
        '{transport: {link: {tls: {root_ca_certificate: "certs/ca.pem"}}, auth: {usrpwd: {user: "trainer", password: "x"}}}}')
    (out / "ca-only.json5").write_text('{transport: {link: {tls: {root_ca_certificate: "certs/ca.pem"}}}}')
    (out / "creds-only.json5").write_text('{transport: {auth: {usrpwd: {user: "trainer", password: "change-me-too"}}}}')
    return out


@pytest.fixture(scope="module")
def routers(configs):
    """Endpoints of three routers: ACL (TLS + usrpwd + ACL), mutual TLS, and usrpwd over TCP."""
    eps = {"acl": f"tls/127.0.0.1:{free_port()}", "mtls": f"tls/127.0.0.1:{free_port()}",
           "usrpwd": f"tcp/127.0.0.1:{free_port()}"}
    procs = [_router(configs / "router-acl.json5", eps["acl"]), _router(configs / "router-mtls.json5", eps["mtls"]),
             _router(configs / "router-usrpwd.json5", eps["usrpwd"])]
    yield eps
    for proc in procs:
        assert stop_process(proc) == 0


@pytest.mark.parametrize("router, endpoint_of, config, error, match", [
    ("acl", None, "wrong-password.json5", AuthenticationError, "refused user 'trainer': wrong password"),
    ("acl", None, "ca-only.json5", AuthenticationError, "requires a user and password"),
    ("acl", None, "creds-only.json5", TlsHandshakeError, "no transport/link/tls/root_ca_certificate"),
    ("acl", "tcp", "creds-only.json5", TlsHandshakeError, "is a TLS listener; connect with tls/"),
    ("acl", "localhost", "trainer-tls-usrpwd.json5", TlsHandshakeError, "not valid for 'localhost'"),
    ("acl", "dead", "trainer-tls-usrpwd.json5", RouterUnreachableError, "nothing accepts connections"),
    ("mtls", None, "client-tls.json5", TlsHandshakeError, "requires a client certificate"),
    ("usrpwd", None, None, AuthenticationError, "requires a user and password"),
])
def test_refusals_are_told_apart(routers, configs, router, endpoint_of, config, error, match):
    endpoint = routers[router]
    host_port = endpoint.split("/", 1)[1]
    endpoint = {None: endpoint, "tcp": f"tcp/{host_port}", "localhost": f"tls/localhost:{host_port.split(':')[1]}",
                "dead": f"tls/127.0.0.1:{free_port()}"}[endpoint_of]
    with pytest.raises(error, match=match) as info:
        open_session(client_of([endpoint], config_file=str(configs / config) if config else None))
    assert isinstance(info.value, ConnectionError) and info.value.endpoints == (endpoint,)


@pytest.mark.parametrize("router, config", [("mtls", "client-mtls.json5"), ("usrpwd", "trainer-usrpwd.json5"),
                                            ("usrpwd", "worker-usrpwd.json5")])
def test_good_credentials_connect(routers, configs, router, config):
    open_session(client_of([routers[router]], config_file=str(configs / config))).close()


def test_acl_lets_each_role_do_only_its_part(routers, configs, scene_root):
    ep = routers["acl"]
    good = start_worker(RUN, ep, scene_root, connect=True, worker_id="good",
                        extra_args=["--zenoh-config", str(configs / "worker-tls-usrpwd.json5")])
    # Workers the ACL denies (the trainer's credentials; a run it has no rules for) do not print
    # "ready": they see that their token does not get through the router, and refuse to start.
    for run, wid, creds in ((RUN, "rogue", "trainer-tls-usrpwd.json5"), ("exp2", "other", "worker-tls-usrpwd.json5")):
        proc = subprocess.run([sys.executable, "-m", "visfly_dist.cli", "worker", "--run-id", run, "--connect", ep,
                               "--worker-id", wid, "--scene-root", str(scene_root), "--backend", "raycast",
                               "--zenoh-config", str(configs / creds)], cwd=REPO, capture_output=True, text=True,
                              timeout=60)
        assert proc.returncode == 2 and "ready" not in proc.stdout, (proc.stdout, proc.stderr)
        assert f"worker {wid!r} declared its liveliness token visfly/{run}/alive/worker/{wid} but a session with " \
               "the same config" in proc.stderr and "access control denies this user the token" in proc.stderr, \
            proc.stderr
    # Sessions that serve anyway, as those workers would have (their declarations are dropped):
    # one with the trainer's credentials, one of another run; they must receive no query.
    served = []
    rogue = open_session(client_of([ep], config_file=str(configs / "trainer-tls-usrpwd.json5")))
    other_run = open_session(client_of([ep], config_file=str(configs / "worker-tls-usrpwd.json5")))
    trainer = open_session(client_of([ep], config_file=str(configs / "trainer-tls-usrpwd.json5")))
    worker = open_session(client_of([ep], config_file=str(configs / "worker-tls-usrpwd.json5")))
    rogue_key, other_key = keys.worker_rpc(RUN, "rogue"), keys.worker_rpc("exp2", "other")
    entities = [rogue.declare_queryable(rogue_key, lambda q: (served.append(q.key_expr), q.reply(q.key_expr, b"x"))),
                rogue.liveliness().declare_token(keys.worker_alive(RUN, "rogue")),
                other_run.declare_queryable(other_key, lambda q: (served.append(q.key_expr), q.reply(q.key_expr, b"x"))),
                other_run.liveliness().declare_token(keys.worker_alive("exp2", "other"))]
    try:
        ok, reply = call(trainer, good.rpc_key, Health().to_message(), timeout=5)
        assert ok and reply["type"] == "health"
        for session, key in ((trainer, rogue_key), (worker, good.rpc_key), (trainer, other_key)):
            assert list(session.get(key, payload=b"x", timeout=2, consolidation=zenoh.ConsolidationMode.NONE)) == []
        assert served == []
        tokens = trainer.liveliness().declare_subscriber(keys.workers_alive_pattern(RUN),
                                                         zenoh.handlers.FifoChannel(16), history=True)
        try:
            seen: set[str] = set()

            def collect() -> set[str]:
                seen.update(keys.worker_id_from_alive_key(str(s.key_expr)) for s in iter(tokens.try_recv, None))
                return seen

            assert wait_for(lambda: "good" in collect(), timeout=60, interval=0.1), seen
            time.sleep(1.0)  # room for a token that should not come (it would travel with the good one)
            assert collect() == {"good"}  # the rogue's token is dropped too
        finally:
            tokens.undeclare()
    finally:
        for entity in entities:
            entity.undeclare()
        for session in (trainer, worker, rogue, other_run):
            session.close()
        stop_process(good)


def test_a_trainer_denied_by_the_acl_gets_access_denied(routers, configs, scene_root):
    ep = routers["acl"]
    # A worker of run exp2 (which the ACL has no rules for) refuses to start; a session that declares
    # what it would have stands in for it: its token and queryable, both dropped by the router.
    worker = open_session(client_of([ep], config_file=str(configs / "worker-tls-usrpwd.json5")))
    entities = [worker.declare_queryable(keys.worker_rpc("exp2", "w"), lambda q: q.reply(q.key_expr, b"x")),
                worker.liveliness().declare_token(keys.worker_alive("exp2", "w"))]
    try:
        agg = make_aggregator(pool={"connect": (ep,), "num_local_workers": 0, "run_id": "exp2", "startup_timeout_s": 2.0,
                                    "zenoh_config": str(configs / "trainer-tls-usrpwd.json5")},
                              scenes={"num_scenes": 1, "agents_per_scene": 1})
        with pytest.raises(AccessDeniedError, match="denies 'trainer' liveliness subscriptions or queries on visfly/exp2"):
            agg.start()
    finally:
        for entity in entities:
            entity.undeclare()
        worker.close()


def test_a_pool_hands_its_config_to_its_local_workers(routers, configs):
    # usrpwd router: a local worker that did not get the file could not join, and start() would fail
    agg = make_aggregator(pool={"connect": (routers["usrpwd"],), "num_local_workers": 1, "run_id": "pooled",
                                "zenoh_config": str(configs / "worker-usrpwd.json5")},
                          scenes={"sources": ("gen:pillars",), "num_scenes": 1, "agents_per_scene": 1})
    with agg:
        assert agg.workers == ["local-0"]
        assert agg.assignment() == {0: "local-0"}


@pytest.mark.parametrize("command", [
    ["worker", "--run-id", "r", "--connect", "tcp/127.0.0.1:7447"],
    ["router", "--listen", "tcp/127.0.0.1:0"],
    ["launch", "--workers", "1", "--run-id", "r", "--connect", "tcp/127.0.0.1:7447"],
    ["train", "hover", "--timesteps", "8"],
    ["eval", "hover", "--checkpoint", "final.zip"],  # made in tmp_path (the cwd) below, never read
    ["bench", "step", "--steps", "1"],
])
def test_every_command_takes_a_zenoh_config_and_names_a_bad_one(tmp_path, command):
    missing = tmp_path / "nowhere.json5"
    (tmp_path / "final.zip").write_bytes(b"")
    out = subprocess.run([sys.executable, "-m", "visfly_dist.cli", *command, "--zenoh-config", str(missing)],
                         cwd=tmp_path, capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": str(REPO)})
    assert out.returncode == 2, out
    assert f"zenoh config file '{missing}' does not exist" in out.stderr, out.stderr


def test_a_local_pool_refuses_credentials_it_cannot_use(configs):
    from visfly_dist.aggregator import PoolConfig
    from visfly_dist.errors import ConfigError

    with pytest.raises(ConfigError, match="sets user/password authentication, but this pool's 2 local worker"):
        PoolConfig(num_local_workers=2, zenoh_config=str(configs / "trainer-usrpwd.json5")).validate()
    PoolConfig(num_local_workers=2, zenoh_config=str(configs / "client-tls.json5")).validate()
    PoolConfig(connect=("tcp/127.0.0.1:7447",), num_local_workers=2,
               zenoh_config=str(configs / "worker-usrpwd.json5")).validate()


def test_launch_hands_its_config_to_its_workers(routers, configs, tmp_path):
    ep = routers["usrpwd"]  # a worker started without the file could not join this router
    launch = subprocess.Popen([sys.executable, "-m", "visfly_dist.cli", "launch", "--workers", "1", "--run-id", "launched",
                               "--connect", ep, "--worker-prefix", "lw", "--scene-root", str(tmp_path),
                               "--backend", "raycast", "--log-dir", str(tmp_path / "logs"),
                               "--zenoh-config", str(configs / "worker-usrpwd.json5")],
                              cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(REPO)},
                              stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    session = open_session(client_of([ep], config_file=str(configs / "trainer-usrpwd.json5")))
    try:
        assert "launch ready" in _read_line(launch, 30.0)
        alive = keys.worker_alive("launched", "lw-0")
        assert wait_for(lambda: [r for r in session.liveliness().get(alive, timeout=1) if r.ok is not None],
                        timeout=120, interval=0.2), (tmp_path / "logs" / "lw-0.log").read_text()
    finally:
        session.close()
        assert stop_process(launch) == 0
