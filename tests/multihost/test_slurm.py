"""``deploy/slurm/workers.sbatch`` against a real single-node Slurm cluster started by the test.

Needs Debian's ``slurmctld slurmd slurm-client munge`` (``apt-get install -y --no-install-recommends
slurmctld slurmd slurm-client munge``); skipped with the reason when they are missing or the
daemons cannot start here.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from tests.aggregator.conftest import make_aggregator, reference, spawn_poses
from tests.helpers import REPO, _read_line, free_port, stop_process, wait_for
from tests.multihost.slurm import SlurmCluster, SlurmError, missing_tools

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

if os.geteuid() != 0:
    pytest.skip("the single-node Slurm cluster runs its daemons as root", allow_module_level=True)
if missing_tools():
    pytest.skip(f"Slurm/munge not installed ({missing_tools()}); apt-get install -y --no-install-recommends "
                "slurmctld slurmd slurm-client munge", allow_module_level=True)

SBATCH = REPO / "deploy" / "slurm" / "workers.sbatch"


@pytest.fixture
def cluster(tmp_path):
    try:
        c = SlurmCluster(tmp_path / "slurm")
    except SlurmError as exc:
        pytest.skip(f"slurmctld/slurmd could not start here: {str(exc)[:1500]}")
    yield c
    c.close()


@pytest.fixture
def router():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen([sys.executable, "-m", "visfly_dist.cli", "router", "--listen", endpoint], cwd=REPO,
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    assert "router ready" in _read_line(proc, 30.0)
    yield endpoint
    assert stop_process(proc) == 0


def _processes_mentioning(text: str) -> list[int]:
    pids = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                if text.encode() in f.read():
                    pids.append(int(pid))
        except OSError:
            pass
    return pids


def test_sbatch_starts_workers_that_serve_a_run_and_scancel_stops_them(cluster, router, tmp_path):
    run_id = f"slurm-{os.getpid()}"
    env = {"PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    out = cluster.run("sbatch", "--parsable", "--ntasks=2", "--cpus-per-task=1", f"--output={tmp_path}/%j.out",
                      f"--export=ALL,ROUTER={router},RUN_ID={run_id},SCENES={tmp_path}", str(SBATCH), env=env)
    job = out.stdout.strip().split(";")[0]
    agg = make_aggregator(pool={"connect": (router,), "num_local_workers": 0, "run_id": run_id, "min_workers": 2},
                          scenes={"sources": ("gen:pillars",), "num_scenes": 2, "agents_per_scene": 2})
    try:
        agg.start()
        assert sorted(agg.workers) == [f"{cluster.node}-0", f"{cluster.node}-1"], (agg.workers, cluster.logs())
        assert set(agg.assignment().values()) == set(agg.workers)
        poses = spawn_poses(agg)
        obs = agg.observe(poses)
        np.testing.assert_allclose(obs.images["depth"], reference(agg, poses)["depth"], atol=1e-4)

        cluster.run("scancel", job)
        assert wait_for(lambda: agg.workers == [], timeout=30), agg.workers
        assert wait_for(lambda: job not in cluster.jobs(), timeout=30), cluster.run("squeue").stdout
        assert wait_for(lambda: _processes_mentioning(run_id) == [], timeout=30), _processes_mentioning(run_id)
    finally:
        agg.close()
    log = (tmp_path / f"{job}.out").read_text()
    assert log.count("ready on run " + run_id) == 2, log
