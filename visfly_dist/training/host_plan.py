"""The host plan: a run sized to the machine it starts on (cores, GPU, memory).

``visfly-dist train`` (and ``eval``, ``bench train``) leave the sizes of a run to this plan unless
they are given: the learner's device, the number of agents, the local scene workers and each
worker's tracing threads, whether two agent groups overlap, and the PPO batch that follows the
number of agents. Every choice comes with one line saying why; the plan is recorded in the run's
``config.json`` (``host_plan``), and every choice stays overridable by its own flag.

The rules:

* **Cores** are the usable ones (:func:`visfly_dist.host.usable_cores`: CPU affinity and cgroup
  quota), never ``os.cpu_count()``. The learner keeps one core (two from 8 cores up: its main
  thread and Zenoh's), the workers share the rest, each tracing with ``cores // workers`` threads,
  so that learner, workers and their threads never ask for more cores than the host has. On 2
  cores learner and workers take turns (the learner waits while the workers render).
* **Device**: ``auto`` is CUDA when torch sees a GPU, else the CPU. ``cuda`` without a usable GPU
  fails before any work, naming torch's build.
* **Workers**: 2 up to 8 cores (measured best on 2), then one per 4 cores, at most 8 (one worker
  with 16 threads stepped 21k env-steps/s at 1,024 agents on a 16-core host; 14 workers with 8
  threads each, 15k).
* **Agents**: the task's default (sized on 2 cores) times a scale, a power of two: half the usable
  cores, at least 8 with a GPU, capped by memory (the rollout must fit a quarter of what is free)
  and at :data:`MAX_AGENTS`.
* **Rollout, minibatch and budget**: more agents take shorter rollouts (the task's length times
  its agents over the plan's, at least :data:`MIN_ROLLOUT_STEPS`), so that an update comes about as
  often as the task was tuned with; the minibatch grows with the rollout (as many minibatches per
  update, each larger) and so does the run's budget of env steps: the run makes as many updates as
  the task's budget did. PPO learned navigation per update, not per env step: 256 x 64 (16,384
  samples an update) with the task's 600k steps makes 36 updates, where 32 x 64 needed about 150
  to reach its goal; 128 x 16 (2,048 samples, as 32 x 64 and 64 x 32) reached 0.96 on unseen
  garages (docs/RESULTS.md).
* **Overlap** (two agent groups through ``send``/``recv``): on from 4 cores, where the learner has
  a core of its own; and whenever every worker is remote.
* **Training videos**: one filmed every tenth of the run from 8 cores (a background thread with its
  own small env); off below, where it would take a core from training.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

from visfly_dist.errors import ConfigError
from visfly_dist.host import available_memory_bytes, usable_cores

if TYPE_CHECKING:
    from visfly_dist.training.config import TrainConfig

MAX_SCALE = 64
MAX_AGENTS = 128
"""The plan gives no run more agents than this: the most whose learning was seen to reach the task's
goal (navigation, 128 agents x 16 steps with overlap: 0.96 on unseen garages; 256 x 16 with twice the
samples an update and steps: 0.87; docs/RESULTS.md)."""
MIN_ROLLOUT_STEPS = 16
"""Rollouts are not shortened below this many steps per agent: GAE over fewer leans on the value
estimate (GPU trainers with thousands of agents keep 16-24)."""
MAX_WORKERS = 8
VIDEO_MIN_CORES = 8
"""Training videos are filmed (in the background) by default from this many usable cores."""
IMAGE_BYTES = 64 * 64 * 4
"""A 64x64 float depth image: the rollout's bytes per agent and step are about this."""


@dataclass(frozen=True)
class HostFacts:
    """What the plan is made from."""

    cores: int
    memory_bytes: int
    gpu: str | None
    gpu_memory_bytes: int = 0

    @classmethod
    def probe(cls) -> "HostFacts":
        """This host, as this process sees it."""
        import torch

        gpu, gpu_memory = None, 0
        if torch.cuda.is_available():
            props = torch.cuda.get_device_properties(0)
            gpu, gpu_memory = props.name, int(props.total_memory)
        return cls(usable_cores(), available_memory_bytes(), gpu, gpu_memory)


@dataclass
class HostPlan:
    """The sizes chosen for a run, and why (one line per choice)."""

    facts: HostFacts
    device: str
    num_envs: int
    workers: int
    worker_threads: int
    overlap: bool
    batch_size: int
    n_steps: int = 0
    timesteps: int = 0
    video_every: int = 0
    reasons: dict[str, str] = field(default_factory=dict)

    def lines(self) -> list[str]:
        """``host plan: <choice> = <value> (<why>)`` for every choice."""
        return [f"host plan: {name} = {getattr(self, name)} ({why})" for name, why in self.reasons.items()]

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["facts"] = asdict(self.facts)
        return out


def check_device(device: str) -> str:
    """``device`` resolved (``auto`` -> ``cuda``/``cpu``); a CUDA device torch cannot use fails now.

    Raises:
        ConfigError: ``cuda`` asked of a CPU-only torch, or of a host where torch sees no GPU.
    """
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        build = ("a CPU-only build" if torch.version.cuda is None
                 else f"built for CUDA {torch.version.cuda}, but it sees no GPU (driver, CUDA_VISIBLE_DEVICES?)")
        raise ConfigError(f"--device {device}: torch {torch.__version__} is {build}; use --device auto or cpu")
    try:
        torch.device(device)
    except RuntimeError as exc:
        raise ConfigError(f"--device {device!r} is not a torch device: {exc}") from None
    return device


def plan_host(facts: HostFacts, device: str, base_envs: int, base_batch: int, base_n_steps: int,
              base_timesteps: int = 0, *, num_envs: int | None = None, workers: int | None = None,
              worker_threads: int | None = None, overlap: bool | None = None, batch_size: int | None = None,
              n_steps: int | None = None, timesteps: int | None = None, remote_only: bool = False,
              team: int = 1, video_every: int | None = None) -> HostPlan:
    """Size a run for ``facts`` (pure: the same facts give the same plan).

    Args:
        facts: the host.
        device: the learner's device, already checked (``cpu``/``cuda...``).
        base_envs, base_batch, base_n_steps, base_timesteps: the task's agents, minibatch, rollout
            length and budget of env steps, tuned on a 2-core CPU host.
        num_envs, workers, worker_threads, overlap, batch_size, n_steps, timesteps, video_every: given
            values, kept as they are.
        remote_only: every worker is remote (``--workers 0``).
        team: agents per team (the agent count stays a multiple of it).
    """
    reasons: dict[str, str] = {}
    cores = facts.cores
    gpu = device.startswith("cuda")
    reasons["device"] = ("given" if device not in ("cpu", "cuda") else
                         f"torch sees {facts.gpu}" if gpu else "no GPU that torch can use")
    if workers is None:
        workers = 0 if remote_only else (2 if cores <= 8 else min(MAX_WORKERS, cores // 4))
        reasons["workers"] = ("every worker is remote" if remote_only else
                              f"{cores} usable cores: 2 up to 8 cores, then one per 4 (at most {MAX_WORKERS})")
    else:
        reasons["workers"] = "given"
    learner_cores = 0 if cores <= 2 else (1 if cores < 8 else 2)
    if worker_threads is None:
        worker_threads = max(1, (cores - learner_cores) // max(workers, 1))
        reasons["worker_threads"] = (f"{cores} cores - {learner_cores} for the learner, shared by {workers} worker(s)" if workers
                                     else "no local worker: unused here (remote workers size their own threads)")
    else:
        reasons["worker_threads"] = "given"
    if num_envs is None:
        scale = _power_of_two_at_most(max(1, cores // 2))
        if gpu:
            scale = max(scale, 8)
        rollout_budget = (facts.gpu_memory_bytes if gpu else facts.memory_bytes) // 4
        while scale > 1 and base_envs * scale * (n_steps or base_n_steps) * IMAGE_BYTES > rollout_budget:
            scale //= 2
        scale = min(scale, MAX_SCALE)
        while scale > 1 and base_envs * scale > MAX_AGENTS:
            scale //= 2
        num_envs = max(team, (base_envs * scale) // team * team)
        reasons["num_envs"] = (f"the task's {base_envs} (sized for 2 cores) x {scale}"
                               + (" (a GPU learner)" if gpu else f" ({cores} usable cores)"))
    else:
        reasons["num_envs"] = "given"
    if n_steps is None:
        n_steps = min(base_n_steps, max(MIN_ROLLOUT_STEPS, round(base_n_steps * base_envs / num_envs)))
        reasons["n_steps"] = (f"the task's {base_n_steps}" if n_steps == base_n_steps else
                              f"the task's {base_n_steps} x {base_envs}/{num_envs} agents, at least {MIN_ROLLOUT_STEPS}: "
                              "updates about as often as the task was tuned with")
    else:
        reasons["n_steps"] = "given"
    growth = max(1, round(n_steps * num_envs / (base_n_steps * base_envs)))   # samples per update, against the task's
    if batch_size is None:
        batch_size = max(2, min(base_batch * growth, n_steps * num_envs))
        reasons["batch_size"] = f"the task's {base_batch} x {growth}: as many minibatches per update, each larger"
    else:
        reasons["batch_size"] = "given"
    if timesteps is None:
        timesteps = base_timesteps * growth
        reasons["timesteps"] = (f"the task's {base_timesteps:,}" if growth == 1 else
                                f"the task's {base_timesteps:,} x {growth}: as many updates, each {growth}x larger")
    else:
        reasons["timesteps"] = "given"
    if overlap is None:
        overlap = remote_only or cores >= 4
        reasons["overlap"] = ("every worker is remote: hide the round trip" if remote_only else
                              f"{cores} cores: the learner has a core of its own" if overlap else
                              f"{cores} cores: learner and workers share them; overlapping would make them wait on each other")
    else:
        reasons["overlap"] = "given"
    if video_every is None:
        video_every = timesteps // 10 if cores >= VIDEO_MIN_CORES else 0
        reasons["video_every"] = (f"{cores} cores: a film every tenth of the run, on a core of its own" if video_every else
                                  f"{cores} cores: no core to spare for films (--video-every STEPS turns them on)")
    else:
        reasons["video_every"] = "given"
    return HostPlan(facts, device, num_envs, workers, worker_threads, overlap, batch_size, n_steps, timesteps,
                    video_every, reasons)


def _power_of_two_at_most(n: int) -> int:
    p = 1
    while p * 2 <= n:
        p *= 2
    return p


def apply_host_plan(cfg: "TrainConfig", facts: HostFacts | None = None, log: Any = print) -> "TrainConfig":
    """``cfg`` (unresolved) with the plan's sizes where it leaves them open, and the plan recorded
    in ``cfg.host_plan``; ``log`` gets one line per choice.

    The plan's ``overlap`` is the tensor trainer's (two agent groups); SB3's ``--overlap`` (a
    lagged rollout) keeps its own default.

    Raises:
        ConfigError: ``--device cuda`` without a GPU torch can use.
    """
    from dataclasses import replace

    from visfly_dist.tasks import task_class
    from visfly_dist.training.config import task_defaults

    given = cfg.size_problems()
    if given:
        raise ConfigError("invalid training config: " + "; ".join(given))
    device = check_device(cfg.device)
    facts = facts or HostFacts.probe()
    base = task_defaults(cfg.task, cfg.algo)
    task_config = task_class(cfg.task).config_class()
    team = task_config.agents_per_scene if task_config.multi_agent else 1
    tensor = cfg.algo == "ppo"
    plan = plan_host(facts, device, base["num_envs"], base["batch_size"], base["n_steps"], base["timesteps"],
                     num_envs=cfg.num_envs, workers=cfg.workers, worker_threads=cfg.worker_threads,
                     overlap=cfg.overlap if tensor else False, batch_size=cfg.batch_size, n_steps=cfg.n_steps,
                     timesteps=cfg.timesteps, remote_only=cfg.workers == 0, team=team, video_every=cfg.video_every)
    if not tensor:
        plan.reasons.pop("overlap", None)
    for line in plan.lines():
        log(line)
    return replace(cfg, device=device, num_envs=plan.num_envs, workers=plan.workers, worker_threads=plan.worker_threads,
                   batch_size=plan.batch_size, n_steps=plan.n_steps, timesteps=plan.timesteps,
                   overlap=plan.overlap if tensor else cfg.overlap, video_every=plan.video_every, host_plan=plan.to_dict())
