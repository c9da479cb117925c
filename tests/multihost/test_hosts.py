"""Training across emulated hosts: a router host, two worker hosts and a trainer host.

Each host is a network namespace on one bridge with its own /dev/shm (see ``netns.py``), so the
traffic between hosts is real TCP or TLS, never shared memory. The trainer is ``drive.py``
(``make_env`` with zero local workers, random actions); every step it takes must succeed.
"""

from __future__ import annotations

import json
import os
import re
import signal
import sys
import time
from pathlib import Path
from typing import Callable

import pytest

from tests.multihost.netns import Host, Lan, namespaces_unavailable, read_line

# Every wait below is for a state (a report, a line, an exit), never a bound on speed: a loaded
# host may take long to get there, so each may take up to WAIT_S before the test fails.
WAIT_S = 180.0
pytestmark = [pytest.mark.slow, pytest.mark.timeout(1800)]

REPO = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
ENV.pop("ZENOH_CONFIG", None)
RUN = "exp1"  # the run id deploy/zenoh/router-acl.json5 allows

_why = namespaces_unavailable()
if _why:
    pytest.skip(f"multi-host tests need network namespaces: {_why}", allow_module_level=True)


def visfly(host: Host, *args: str, stdin: bool = False):
    return host.spawn([sys.executable, "-m", "visfly_dist.cli", *args], env=ENV, stdin=stdin)


def start_router(host: Host, endpoint: str, config: Path | None = None):
    proc = visfly(host, "router", "--listen", endpoint, *(["--zenoh-config", str(config)] if config else []))
    line = read_line(proc, WAIT_S)
    assert "router ready" in line, (line, proc.stderr_text())
    return proc


def start_worker(host: Host, endpoint: str, worker_id: str, scene_root: Path, config: Path | None = None):
    proc = visfly(host, "worker", "--run-id", RUN, "--connect", endpoint, "--worker-id", worker_id,
                  "--scene-root", str(scene_root), "--backend", "raycast", "--lease-ms", "1000",
                  *(["--zenoh-config", str(config)] if config else []))
    line = read_line(proc, WAIT_S)
    assert f"worker {worker_id} ready" in line, (line, proc.stderr_text())
    return proc


def start_trainer(host: Host, endpoint: str, config: Path | None = None):
    argv = [sys.executable, str(REPO / "tests" / "multihost" / "drive.py"), "--connect", endpoint, "--run-id", RUN]
    return host.spawn(argv + (["--zenoh-config", str(config)] if config else []), env=ENV, stdin=True)


def wait_report(trainer, condition: Callable[[dict], bool], what: str, timeout: float = WAIT_S) -> dict:
    """Read the trainer's reports until one satisfies ``condition``; fail with ``what`` otherwise."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        line = read_line(trainer, deadline - time.monotonic())
        if not line:
            break
        last = json.loads(line)
        if "steps" in last and condition(last):
            return last
    pytest.fail(f"trainer: {what} not seen within {timeout} s; last report {last}; exit {trainer.poll()}; "
                f"stderr tail: {trainer.stderr_text()[-3000:]}\n{others_stderr(trainer)}")


def others_stderr(trainer) -> str:
    """The stderr tails of the lan's other processes (routers, workers), to tell why a report did not come."""
    out = []
    for proc in trainer.host.lan.procs:
        if proc is not trainer:
            out.append(f"--- {proc.host.name}: {' '.join(proc.argv[3:])[:160]} (exit {proc.poll()}):\n{proc.stderr_text()[-1500:]}")
    return "\n".join(out)


def serving(report: dict) -> set[str]:
    return set(report["assignment"].values())


def stop_trainer(trainer) -> int:
    trainer.stdin.write("stop\n")
    trainer.stdin.flush()
    done = wait_done(trainer)
    assert trainer.wait(WAIT_S) == 0, trainer.stderr_text()[-3000:]
    return done


def wait_done(trainer) -> int:
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        line = read_line(trainer, deadline - time.monotonic())
        if not line:
            break
        if "done" in (msg := json.loads(line)):
            return msg["done"]
    pytest.fail(f"trainer did not finish: {trainer.stderr_text()[-3000:]}")


def stop_cleanly(*procs) -> None:
    for proc in procs:
        proc.send_signal(signal.SIGTERM)
    for proc in procs:
        assert proc.wait(WAIT_S) == 0, proc.stderr_text()[-2000:]


def test_tcp_training_survives_a_killed_worker_a_partition_and_a_router_restart(tmp_path):
    with Lan(71) as lan:
        r, b, c, t = lan.host("router"), lan.host("wb"), lan.host("wc"), lan.host("tr")
        ep = f"tcp/{r.address}:7447"
        router = start_router(r, ep)
        wb, wc = start_worker(b, ep, "wb", tmp_path), start_worker(c, ep, "wc", tmp_path)
        trainer = start_trainer(t, ep)
        rep = wait_report(trainer, lambda m: m["steps"] >= 200 and serving(m) == {"wb", "wc"},
                          "200 steps served by both workers")

        os.killpg(wb.pid, signal.SIGKILL)  # a worker host's process dies
        rep = wait_report(trainer, lambda m, s=rep["steps"]: m["steps"] >= s + 40 and serving(m) == {"wc"},
                          "training going on with wc alone after wb was killed")
        wb = start_worker(b, ep, "wb", tmp_path)
        rep = wait_report(trainer, lambda m: serving(m) == {"wb", "wc"}, "the restarted wb getting work")

        c.link(False)  # wc's cable out for 10 s: its lease expires, its scene moves to wb
        unplugged = time.monotonic()
        rep = wait_report(trainer, lambda m, s=rep["steps"]: m["steps"] >= s + 40 and serving(m) == {"wb"},
                          "training going on with wb alone while wc is cut off")
        time.sleep(max(0.0, 10.0 - (time.monotonic() - unplugged)))
        c.link(True)
        rep = wait_report(trainer, lambda m: "wc" in m["workers"] and serving(m) == {"wb", "wc"},
                          "wc rejoining after the partition and getting work")
        assert wc.poll() is None, "the partitioned worker must survive and reconnect"
        # It holds only the scenes it serves now: the ones it served before the partition were unloaded.
        wait_report(trainer, lambda m: m["held"] is not None and all(
            keys == sorted(k for w, k in m["served"] if w == wid) for wid, keys in m["held"].items()),
            "each worker holding exactly the scenes it serves")

        router.send_signal(signal.SIGTERM)  # router restart
        assert router.wait(WAIT_S) == 0, router.stderr_text()
        router = start_router(r, ep)
        wait_report(trainer, lambda m, s=rep["steps"]: m["steps"] >= s + 40 and serving(m) == {"wb", "wc"},
                    "training going on with both workers after the router restart")
        # Loads whose replies the restart lost left no scene behind.
        wait_report(trainer, lambda m: m["held"] is not None and all(
            keys == sorted(k for w, k in m["served"] if w == wid) for wid, keys in m["held"].items()),
            "each worker holding exactly the scenes it serves after the router restart")

        assert stop_trainer(trainer) > 300
        stop_cleanly(wb, wc, router)
        assert all(h.pids() == [] for h in lan.hosts), "a process was left behind in a host"
    assert lan.leftover_namespaces() == [], "a namespace was left behind"


def test_tls_usrpwd_acl_training_and_typed_refusals(tmp_path, deploy_configs):
    with Lan(72) as lan:
        r, b, c, t = lan.host("router"), lan.host("wb"), lan.host("wc"), lan.host("tr")
        z = deploy_configs(r.address)
        ep = f"tls/{r.address}:7447"
        router = start_router(r, ep, z / "router-acl.json5")  # TLS + user/password + per-run ACL
        wb = start_worker(b, ep, "wb", tmp_path, z / "worker-tls-usrpwd.json5")
        wc = start_worker(c, ep, "wc", tmp_path, z / "worker-tls-usrpwd.json5")
        trainer = start_trainer(t, ep, z / "trainer-tls-usrpwd.json5")
        wait_report(trainer, lambda m: m["steps"] >= 200 and serving(m) == {"wb", "wc"},
                    "200 steps over TLS + user/password served by both workers")
        assert stop_trainer(trainer) >= 200

        (z / "wrong-password.json5").write_text(
            '{transport: {link: {tls: {root_ca_certificate: "certs/ca.pem"}}, '
            'auth: {usrpwd: {user: "worker", password: "wrong"}}}}')
        (z / "no-ca.json5").write_text('{transport: {auth: {usrpwd: {user: "worker", password: "change-me"}}}}')
        refusals = [
            ("wrong-password.json5", ep, "the router refused user 'worker': wrong password"),
            ("no-ca.json5", ep, "TLS to .*: the config gives no transport/link/tls/root_ca_certificate"),
            ("worker-tls-usrpwd.json5", f"tls/{r.address}:7448", "nothing accepts connections at"),
        ]
        for config, endpoint, message in refusals:
            proc = visfly(t, "worker", "--run-id", RUN, "--connect", endpoint, "--scene-root", str(tmp_path),
                          "--zenoh-config", str(z / config))
            assert proc.wait(WAIT_S) == 2, (config, proc.stderr_text())
            assert re.search(message, proc.stderr_text()), (config, proc.stderr_text())
        stop_cleanly(wb, wc, router)
        assert all(h.pids() == [] for h in lan.hosts), "a process was left behind in a host"
    assert lan.leftover_namespaces() == [], "a namespace was left behind"
