"""The host plan (pure: facts in, sizes out), the host probes on fake cgroup files, and --device checks."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from visfly_dist.errors import ConfigError
from visfly_dist.host import cgroup_cpu_limit, usable_cores
from visfly_dist.training.config import TrainConfig
from visfly_dist.training.host_plan import HostFacts, apply_host_plan, check_device, plan_host

GIB = 1 << 30
LAPTOP = HostFacts(cores=2, memory_bytes=16 * GIB, gpu=None)
WORKSTATION = HostFacts(cores=16, memory_bytes=120 * GIB, gpu="NVIDIA H200", gpu_memory_bytes=140 * GIB)


def navigation(facts: HostFacts, device: str = "cpu", **given) -> object:
    return plan_host(facts, device, base_envs=32, base_batch=512, base_n_steps=64, base_timesteps=600_000, **given)


def test_a_two_core_laptop_keeps_the_sizes_the_task_was_tuned_with() -> None:
    plan = navigation(LAPTOP)
    assert (plan.num_envs, plan.batch_size, plan.workers, plan.worker_threads, plan.overlap) == (32, 512, 2, 1, False)
    assert (plan.n_steps, plan.timesteps) == (64, 600_000)
    assert plan.video_every == 0   # no core to spare for films


@pytest.mark.parametrize("cores", [1, 2, 3, 4, 6, 8, 12, 16, 32, 64, 128])
def test_learner_workers_and_their_threads_never_ask_for_more_cores_than_the_host_has(cores: int) -> None:
    plan = navigation(HostFacts(cores=cores, memory_bytes=64 * GIB, gpu=None))
    learner = 0 if cores <= 2 else (1 if cores < 8 else 2)
    assert plan.workers * plan.worker_threads + learner <= max(cores, plan.workers)
    assert plan.worker_threads >= 1 and plan.workers >= 1
    assert plan.batch_size <= 64 * plan.num_envs and plan.num_envs % 32 == 0
    assert set(plan.reasons) == {"device", "workers", "worker_threads", "num_envs", "n_steps", "batch_size", "timesteps",
                                 "overlap", "video_every"}
    # an update comes about as often as on 2 cores, over a rollout at least as large; as many updates in the run
    rollout = plan.n_steps * plan.num_envs
    assert 16 <= plan.n_steps <= 64 and rollout >= 64 * 32 and plan.batch_size * 4 == rollout
    assert plan.timesteps * (64 * 32) == 600_000 * rollout


def test_a_gpu_workstation_gets_more_agents_shorter_rollouts_larger_minibatches_and_overlap() -> None:
    plan = navigation(WORKSTATION, "cuda")
    assert plan.workers == 4 and plan.worker_threads == 3      # 4 x 3 + 2 for the learner = 14 of 16 cores
    assert plan.num_envs == 128 and plan.n_steps == 16 and plan.overlap   # at most MAX_AGENTS
    assert plan.batch_size == 512 and plan.timesteps == 600_000   # 2,048 samples an update, as the task's
    assert plan.video_every == 60_000                          # a film every tenth of the run
    assert "NVIDIA H200" in plan.reasons["device"]
    assert any("host plan: num_envs = 128" in line for line in plan.lines())


def test_given_values_are_kept_and_said_so() -> None:
    plan = navigation(WORKSTATION, "cuda", num_envs=64, workers=14, worker_threads=1, overlap=False, batch_size=128,
                      n_steps=8, timesteps=1000, video_every=0)
    assert (plan.num_envs, plan.workers, plan.worker_threads, plan.overlap, plan.batch_size) == (64, 14, 1, False, 128)
    assert (plan.n_steps, plan.timesteps, plan.video_every) == (8, 1000, 0)
    assert all(why == "given" for name, why in plan.reasons.items() if name != "device")
    follows = navigation(WORKSTATION, "cuda", num_envs=64)         # rollout, minibatch and budget follow given agents
    assert (follows.n_steps, follows.batch_size, follows.timesteps) == (32, 512, 600_000)
    longer = navigation(WORKSTATION, "cuda", num_envs=64, n_steps=64)
    assert (longer.batch_size, longer.timesteps) == (1024, 1_200_000)


def test_no_plan_goes_past_the_largest_batch_whose_learning_was_checked() -> None:
    wide = plan_host(WORKSTATION, "cuda", base_envs=64, base_batch=512, base_n_steps=32, base_timesteps=600_000)
    assert (wide.num_envs, wide.n_steps, wide.batch_size, wide.timesteps) == (128, 16, 512, 600_000)
    assert navigation(HostFacts(cores=128, memory_bytes=512 * GIB, gpu=None)).num_envs == 128
    hover = plan_host(WORKSTATION, "cuda", base_envs=16, base_batch=512, base_n_steps=128, base_timesteps=100_000)
    assert (hover.num_envs, hover.n_steps, hover.batch_size, hover.timesteps) == (128, 16, 512, 100_000)


def test_memory_caps_the_agents_and_teams_stay_whole() -> None:
    small = HostFacts(cores=32, memory_bytes=1 * GIB, gpu=None)   # 16x: a 0.5 GiB rollout, over a quarter of 1 GiB
    assert navigation(small).num_envs < 32 * 16
    team = plan_host(HostFacts(cores=16, memory_bytes=64 * GIB, gpu=None), "cpu", base_envs=15, base_batch=480,
                     base_n_steps=128, team=3)
    assert team.num_envs % 3 == 0 and team.num_envs >= 15


def test_remote_workers_only_need_no_local_worker_and_overlap() -> None:
    plan = navigation(LAPTOP, remote_only=True)
    assert plan.workers == 0 and plan.overlap
    assert "no local worker" in plan.reasons["worker_threads"]  # not "shared by 1 worker(s)"


def test_cuda_without_a_usable_gpu_fails_naming_torchs_build() -> None:
    if torch.cuda.is_available():
        pytest.skip("this host has a GPU torch can use")
    with pytest.raises(ConfigError, match=rf"torch {torch.__version__.split('+')[0]}.*(CPU-only|sees no GPU)"):
        check_device("cuda")
    assert check_device("auto") == "cpu" and check_device("cpu") == "cpu"
    with pytest.raises(ConfigError, match="not a torch device"):
        check_device("tpu-9")


def test_apply_host_plan_fills_the_config_and_records_the_plan() -> None:
    lines: list[str] = []
    cfg = apply_host_plan(TrainConfig(task="navigation", algo="ppo"), LAPTOP, log=lines.append)
    assert (cfg.device, cfg.num_envs, cfg.workers, cfg.worker_threads, cfg.batch_size) == ("cpu", 64, 2, 1, 512)
    assert len(lines) == 9 and all(line.startswith("host plan: ") for line in lines)
    assert (cfg.n_steps, cfg.timesteps) == (32, 600_000)
    assert cfg.video_every == 0
    recorded = TrainConfig.from_dict(json.loads(json.dumps(cfg.resolved().to_dict())))
    assert recorded.host_plan["facts"]["cores"] == 2 and recorded.host_plan["num_envs"] == 64
    sb3 = apply_host_plan(TrainConfig(task="navigation", algo="sb3-ppo", workers=0, connect=("tcp/127.0.0.1:1",)),
                          WORKSTATION, log=lines.append)
    assert sb3.overlap is None and sb3.resolved().overlap is True   # SB3's lagged overlap keeps its own default


def test_a_bad_size_fails_before_the_plan_chooses_or_prints_anything() -> None:
    lines: list[str] = []
    with pytest.raises(ConfigError) as info:
        apply_host_plan(TrainConfig(task="navigation", algo="ppo", num_envs=-3, n_steps=0), LAPTOP, log=lines.append)
    assert str(info.value) == "invalid training config: num_envs=-3 must be an int >= 1; n_steps=0 must be an int >= 1"
    assert lines == []  # nothing derived from the bad sizes (a batch size of "512 x 1" for -3 envs) is said
    bad = TrainConfig(task="navigation", algo="ppo", num_envs=-3, n_steps=4, batch_size=64).resolved()
    assert not any("batch_size" in p for p in bad.problems())  # only the given mistake, not what follows from it


def test_cgroup_quota_v2_and_v1(tmp_path: Path) -> None:
    proc = tmp_path / "cgroup"
    (tmp_path / "fs" / "job").mkdir(parents=True)
    proc.write_text("0::/job\n")
    (tmp_path / "fs" / "job" / "cpu.max").write_text("max 100000\n")
    (tmp_path / "fs" / "cpu.max").write_text("250000 100000\n")     # the parent's quota binds
    assert cgroup_cpu_limit(tmp_path / "fs", proc) == 2.5
    (tmp_path / "fs" / "cpu.max").write_text("max 100000\n")
    assert cgroup_cpu_limit(tmp_path / "fs", proc) is None

    v1 = tmp_path / "v1"
    (v1 / "cpu,cpuacct" / "docker" / "abc").mkdir(parents=True)
    (v1 / "cpu,cpuacct" / "docker" / "abc" / "cpu.cfs_quota_us").write_text("150000\n")
    (v1 / "cpu,cpuacct" / "docker" / "abc" / "cpu.cfs_period_us").write_text("100000\n")
    proc.write_text("4:cpu,cpuacct:/docker/abc\n3:memory:/docker/abc\n")
    assert cgroup_cpu_limit(v1, proc) == 1.5


def test_usable_cores_follow_the_affinity() -> None:
    import os

    before = os.sched_getaffinity(0)
    try:
        os.sched_setaffinity(0, {min(before)})
        assert usable_cores() == 1
    finally:
        os.sched_setaffinity(0, before)
    assert usable_cores() == len(before) or cgroup_cpu_limit() is not None


def test_solid_components_keep_touching_objects_apart() -> None:
    import trimesh

    from visfly_dist.scenes.solids import solid_components

    a = trimesh.creation.box((1, 1, 1))
    b = trimesh.creation.box((1, 1, 1))
    b.apply_translation((1, 0, 0))                                     # shares a face's corners with a
    vertices = np.concatenate([a.vertices, b.vertices])
    faces = np.concatenate([a.faces, b.faces + len(a.vertices)])
    groups = np.repeat([0, 1], [len(a.vertices), len(b.vertices)])
    merged, _ = solid_components(vertices, faces)
    apart, solid = solid_components(vertices, faces, groups)
    assert len(np.unique(merged)) == 1                                  # merged vertices join the boxes
    assert len(np.unique(apart)) == 2 and solid.all()
    assert set(apart[: len(a.faces)]) != set(apart[len(a.faces):])
