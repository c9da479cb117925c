"""Emulated hosts for tests: Linux network namespaces on one bridge, each process with its own /dev/shm.

A :class:`Lan` makes a "switch" namespace holding a bridge and one namespace per host, joined to
the bridge by a veth pair created directly inside the namespaces (no interface ever exists in the
caller's namespace, and nothing routes to it). Hosts get ``10.<net>.0.<i>/24``. Every process is
started with ``ip netns exec HOST unshare --mount`` and mounts a fresh tmpfs on /dev/shm, so Zenoh
shared memory cannot cross hosts. :meth:`Lan.close` SIGKILLs every process it started and deletes
every namespace; it is idempotent.
"""

from __future__ import annotations

import os
import queue
import shutil
import signal
import subprocess
import tempfile
import threading
import time
from typing import Sequence

_SHM = 'mount -t tmpfs -o size=256m,mode=1777 tmpfs /dev/shm && exec "$@"'


def namespaces_unavailable() -> str | None:
    """Why network namespaces cannot be made here (None when they can)."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    for tool in ("ip", "unshare", "mount"):
        if shutil.which(tool) is None:
            return f"{tool!r} is not installed"
    probe = f"vfprobe{os.getpid()}"
    made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if made.returncode != 0:
        return f"cannot create a network namespace: {made.stderr.strip()}"
    try:
        bridge = subprocess.run(["ip", "-n", probe, "link", "add", "br0", "type", "bridge"], capture_output=True, text=True)
        if bridge.returncode != 0:
            return f"cannot create a bridge in a namespace: {bridge.stderr.strip()}"
        shm = subprocess.run(["ip", "netns", "exec", probe, "unshare", "--mount", "--propagation", "private",
                              "sh", "-c", _SHM, "sh", "true"], capture_output=True, text=True)
        if shm.returncode != 0:
            return f"cannot mount a private /dev/shm: {shm.stderr.strip()}"
    finally:
        subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True)


class Host:
    """One emulated host: a namespace with ``eth0`` at ``address`` on the lan's bridge."""

    def __init__(self, lan: "Lan", name: str, index: int) -> None:
        self.lan, self.name, self.index = lan, name, index
        self.ns = f"{lan.prefix}{name}"
        self.address = f"10.{lan.net}.0.{index}"
        _ip("netns", "add", self.ns)
        _ip("link", "add", "eth0", "netns", self.ns, "type", "veth", "peer", "name", f"p{index}", "netns", lan.switch)
        _ip("-n", lan.switch, "link", "set", f"p{index}", "master", "br0")
        _ip("-n", lan.switch, "link", "set", f"p{index}", "up")
        _ip("-n", self.ns, "addr", "add", f"{self.address}/24", "dev", "eth0")
        _ip("-n", self.ns, "link", "set", "eth0", "up")
        _ip("-n", self.ns, "link", "set", "lo", "up")

    def spawn(self, argv: Sequence[str], env: dict[str, str] | None = None, stdin: bool = False) -> subprocess.Popen:
        """Start ``argv`` on this host with a private /dev/shm; stdout is a pipe, stderr a temp file.

        The returned Popen has ``stderr_text()``. Its pid is the command's own (every wrapper execs).
        """
        err = tempfile.TemporaryFile(mode="w+b")
        proc = subprocess.Popen(
            ["ip", "netns", "exec", self.ns, "unshare", "--mount", "--propagation", "private",
             "sh", "-c", _SHM, "sh", *argv],
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=err,
            env=env, start_new_session=True, text=True)

        def stderr_text() -> str:
            err.seek(0)
            return err.read().decode(errors="replace")

        proc.stderr_text = stderr_text
        proc.argv, proc.host = list(argv), self
        proc.lines = queue.Queue()
        threading.Thread(target=_pump, args=(proc,), daemon=True).start()
        self.lan.procs.append(proc)
        return proc

    def link(self, up: bool) -> None:
        """Plug (``True``) or unplug this host's cable at the switch."""
        _ip("-n", self.lan.switch, "link", "set", f"p{self.index}", "up" if up else "down")

    def pids(self) -> list[int]:
        """Processes still running in this host's namespace."""
        out = subprocess.run(["ip", "netns", "pids", self.ns], capture_output=True, text=True).stdout
        return [int(p) for p in out.split()]


class Lan:
    """A bridge and the hosts on it; use as a context manager."""

    def __init__(self, net: int) -> None:
        self.net = net
        self.prefix = f"vf{os.getpid()}-{net}-"
        self.switch = f"{self.prefix}sw"
        self.hosts: list[Host] = []
        self.procs: list[subprocess.Popen] = []
        _ip("netns", "add", self.switch)
        try:
            _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
            _ip("-n", self.switch, "link", "set", "br0", "up")
        except BaseException:
            self.close()
            raise

    def host(self, name: str) -> Host:
        try:
            h = Host(self, name, len(self.hosts) + 1)
        except BaseException:
            self.close()
            raise
        self.hosts.append(h)
        return h

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            if proc.stdin is not None:
                proc.stdin.close()
        self.procs = []
        for ns in [h.ns for h in self.hosts] + [self.switch]:
            for pid in subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True).stdout.split():
                os.kill(int(pid), signal.SIGKILL)  # only processes inside a namespace this lan made
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        self.hosts = []

    def leftover_namespaces(self) -> list[str]:
        """Namespaces of this lan that still exist (empty after :meth:`close`)."""
        names = os.listdir("/run/netns") if os.path.isdir("/run/netns") else []
        return [n for n in names if n.startswith(self.prefix)]

    def __enter__(self) -> "Lan":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _pump(proc: subprocess.Popen) -> None:
    for line in proc.stdout:
        proc.lines.put(line)
    proc.lines.put("")
    proc.stdout.close()


def read_line(proc: subprocess.Popen, timeout: float) -> str:
    """The next stdout line of a process :meth:`Host.spawn` started ("" on timeout or EOF)."""
    try:
        return proc.lines.get(timeout=max(0.0, timeout))
    except queue.Empty:
        return ""
