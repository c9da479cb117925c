"""A throw-away single-node Slurm cluster (munged, slurmctld, slurmd) in a temporary folder.

Everything it uses lives in that folder: its own munge key and socket, ``slurm.conf`` (found by the
daemons and the client commands through ``SLURM_CONF``), spool and state folders, logs, and fresh
TCP ports on 127.0.0.1. Nothing under /etc is read or changed. :meth:`SlurmCluster.close` cancels
every job, stops the daemons it started and is idempotent.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path

TOOLS = ("munged", "slurmctld", "slurmd", "sbatch", "scancel", "squeue", "sinfo")


def missing_tools() -> list[str]:
    """The Slurm and munge programs that are not installed."""
    return [t for t in TOOLS if shutil.which(t) is None]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class SlurmError(RuntimeError):
    """The cluster did not come up; the message carries the daemons' logs."""


class SlurmCluster:
    """One node called after this host, one partition ``test``; jobs run as root."""

    def __init__(self, folder: Path, cpus: int = 2) -> None:
        self.folder = folder
        self.procs: list[subprocess.Popen] = []
        folder.mkdir(parents=True, exist_ok=True)
        os.chmod(folder, 0o700)
        for sub in ("munge", "spool", "state", "log"):
            (folder / sub).mkdir(exist_ok=True)
            os.chmod(folder / sub, 0o700)
        self.socket = folder / "munge" / "munge.socket"
        key = folder / "munge" / "munge.key"
        key.write_bytes(os.urandom(1024))
        os.chmod(key, 0o600)
        self.node = socket.gethostname().split(".")[0]
        self.conf = folder / "slurm.conf"
        self.conf.write_text("\n".join([
            "ClusterName=visflytest",
            f"SlurmctldHost={self.node}(127.0.0.1)",
            f"SlurmctldPort={_free_port()}",
            f"SlurmdPort={_free_port()}",
            "SlurmUser=root",
            "SlurmdUser=root",
            "AuthType=auth/munge",
            "CredType=cred/munge",
            f"AuthInfo=socket={self.socket}",
            f"StateSaveLocation={folder / 'state'}",
            f"SlurmdSpoolDir={folder / 'spool'}",
            f"SlurmctldPidFile={folder / 'slurmctld.pid'}",
            f"SlurmdPidFile={folder / 'slurmd.pid'}",
            f"SlurmctldLogFile={folder / 'log' / 'slurmctld.log'}",
            f"SlurmdLogFile={folder / 'log' / 'slurmd.log'}",
            "ProctrackType=proctrack/linuxproc",
            "TaskPlugin=task/none",
            "MpiDefault=none",
            "SwitchType=switch/none",
            "JobAcctGatherType=jobacct_gather/none",
            "AccountingStorageType=accounting_storage/none",
            "SelectType=select/cons_tres",
            "SelectTypeParameters=CR_CPU",
            "ReturnToService=2",
            "KillWait=5",
            "InactiveLimit=0",
            "MinJobAge=5",
            f"NodeName={self.node} NodeAddr=127.0.0.1 CPUs={cpus} State=UNKNOWN",
            "PartitionName=test Nodes=ALL Default=YES MaxTime=INFINITE State=UP",
            "",
        ]))
        self.env = {**os.environ, "SLURM_CONF": str(self.conf)}
        try:
            self._start(["munged", "-F", "-f", f"--socket={self.socket}", f"--key-file={key}",
                         f"--pid-file={folder / 'munge' / 'munged.pid'}", f"--log-file={folder / 'log' / 'munged.log'}",
                         f"--seed-file={folder / 'munge' / 'munged.seed'}"])
            self._wait(lambda: self.socket.exists(), 10, "munged socket")
            self._start(["slurmctld", "-D", "-i"])
            self._start(["slurmd", "-D"])
            self._wait(self._node_idle, 30, "node idle in sinfo")
        except BaseException:
            self.close()
            raise

    def _start(self, argv: list[str]) -> None:
        log = open(self.folder / "log" / f"{argv[0]}.out", "wb")
        self.procs.append(subprocess.Popen(argv, env=self.env, stdin=subprocess.DEVNULL, stdout=log,
                                           stderr=subprocess.STDOUT, start_new_session=True))
        log.close()

    def logs(self) -> str:
        return "\n".join(f"--- {p.name}\n{p.read_text(errors='replace')[-2000:]}"
                         for p in sorted((self.folder / "log").iterdir()))

    def _wait(self, condition, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not condition():
            dead = [p.args[0] for p in self.procs if p.poll() is not None]
            if dead or time.monotonic() > deadline:
                raise SlurmError(f"{what} not reached (exited: {dead}):\n{self.logs()}")
            time.sleep(0.2)

    def _node_idle(self) -> bool:
        out = self.run("sinfo", "-h", "-o", "%T", check=False)
        return out.returncode == 0 and out.stdout.strip().rstrip("*") == "idle"

    def run(self, *argv: str, check: bool = True, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
        """Run a Slurm client command against this cluster."""
        return subprocess.run(list(argv), env={**self.env, **(env or {})}, capture_output=True, text=True,
                              timeout=30, check=check)

    def jobs(self) -> list[str]:
        """Ids of the jobs the controller still knows as pending or running."""
        out = self.run("squeue", "-h", "-o", "%i %T")
        return [line.split()[0] for line in out.stdout.splitlines() if line.split()[1] in ("PENDING", "RUNNING", "COMPLETING")]

    def close(self) -> None:
        if any(p.poll() is None for p in self.procs[1:2]):  # slurmctld still up: cancel what is left
            subprocess.run(["scancel", "--full", "-p", "test"], env=self.env, capture_output=True, timeout=30)
        for proc in reversed(self.procs):
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(15)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait()
        self.procs = []
