"""Typed configuration of a PPO training run, with per-task defaults sized for a small CPU host.

``TrainConfig`` holds every setting of ``visfly-dist train``; fields left ``None`` take the task's
value from ``TASK_DEFAULTS`` in :meth:`TrainConfig.resolved`. ``validate()`` reports every problem
at once, before any worker starts. This module imports no torch, so ``--help`` stays fast.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, TypeGuard

from visfly_dist.errors import ConfigError

BACKBONES = ("visfly-cnn", "resnet-tiny", "mobilenet-tiny", "efficientnet-tiny")
PPO_ALGOS = ("ppo", "sb3-ppo")
_SIZES = (("timesteps", 1), ("num_envs", 1), ("n_steps", 1), ("batch_size", 2), ("video_every", 0))
"""The sizes the host plan may choose, and their lowest values."""


def _int_at_least(value: Any, low: int) -> TypeGuard[int]:
    return isinstance(value, int) and not isinstance(value, bool) and value >= low


ALGOS = (*PPO_ALGOS, "bptt", "shac")

_BASE: dict[str, Any] = dict(algo="sb3-ppo", num_envs=16, timesteps=150_000, n_steps=128, batch_size=512,
                             n_epochs=5, log_std_init=0.0, lr=3e-4, horizon=32, gradient={})
"""Every task's defaults unless its row says otherwise (SB3's initial log std: 0)."""


def _task(**changes: Any) -> dict[str, Any]:
    return {**_BASE, **changes}


TASK_DEFAULTS: dict[str, dict[str, Any]] = {
    # Budgets for about 5-30 minutes on a shared 2-core CPU host (docs/RESULTS.md has what each
    # reached): navigation measured at about 170 env steps/s with PPO updates included (16 envs,
    # 64x64 depth), 60 under heavy outside load; hover about 450 (100k steps: 0.99 deterministic
    # success), racing about 200; landing, gap crossing and tracking render images like navigation
    # (tracking: 250k steps, 1.00 deterministic success, 45 min at 94 steps/s under outside load).
    # Navigation starts its action noise at std 0.37 (log -1) instead of SB3's 1: with std 1 on
    # actions clipped to [-1, 1] the sampled policy acts far more gently than its mean, and the
    # deterministic policy (0.12 success against 0.66 sampled) did not fly what training learned.
    # Navigation (new garages during training, NavigationConfig.swap_every_resets): 600k steps.
    # 32 envs x 64 steps (the same 2,048 samples per update as 16 x 128) spread the per-step costs
    # of the learner and the workers over twice the agents: 1.15x the env steps/s of the whole
    # loop, and it learned faster per env step: 0.95 deterministic success on unseen garages in
    # 16 min, against 0.90 for 16 x 128 (docs/RESULTS.md).
    # The tensor PPO (``ppo``) reached 0.93 [0.86, 0.97] deterministic success on unseen garages at
    # 600k steps with these settings, SB3's loop 0.95 [0.89, 0.98] (docs/RESULTS.md); interleaved on 2
    # cores its whole loop ran at 1.02-1.30x SB3's (BENCHMARKS.md).
    # Three passes over each rollout instead of five (fewer updates, as the fast systems train): the
    # update was 60-70% of the loop on 2 cores; 0.94 [0.88, 0.97] deterministic success on unseen
    # garages at 600k steps, against 0.93 with five (docs/RESULTS.md).
    # 64 envs x 32 steps (the same 2,048 samples per update again): the per-step costs spread over
    # twice the agents, 1.13-1.19x the whole loop's env steps/s of 32 x 64 on 2 cores (BENCHMARKS.md);
    # 0.95 [0.89, 0.98] deterministic success on unseen garages at 600k steps (docs/RESULTS.md).
    "navigation": _task(algo="ppo", num_envs=64, timesteps=600_000, n_steps=32, batch_size=512, n_epochs=3,
                        log_std_init=-1.0),
    # Hover and tracking judge success at the time limit; since that end is a truncation like a failed
    # one (session 15), the tensor PPO reached 1.00 deterministic success on both (SB3's loop before
    # the change: hover 0.99, tracking 1.00): their default since (docs/RESULTS.md).
    "hover": _task(algo="ppo", timesteps=100_000),
    # Landing's reward is differentiable (tasks/landing.py): BPTT landed 1.00 of 100 episodes from
    # the whole spawn box after 50k steps (``gradient``: the settings of bptt/shac runs), where PPO
    # (``--algo sb3-ppo``; its spawn curriculum reached the full box at 186k of 300k steps) reached 0.31.
    "landing": _task(algo="bptt", timesteps=300_000, log_std_init=-1.0,
                     gradient=dict(num_envs=8, timesteps=100_000, horizon=16, lr=3e-3)),
    # Gap crossing (5 teams of 3, LV velocity actions, walls whose gap moves): 400k steps; 0.94
    # deterministic team success on unseen walls with SB3's loop (15 min at about 450 env steps/s),
    # 0.95 with the tensor PPO (session 14), its default since. Navigation at 400k steps (0.80
    # deterministic) did no better than at 242k (0.83).
    "gap_crossing": _task(algo="ppo", num_envs=15, timesteps=400_000, batch_size=480, log_std_init=-1.0),
    "racing": _task(timesteps=300_000),
    "tracking": _task(algo="ppo", timesteps=250_000),
}
"""The one table of per-task defaults: the algorithm ``visfly-dist train TASK`` uses without
``--algo`` (``ppo``, the tensor trainer, where it was measured to reach ``sb3-ppo``'s deterministic
success at the same env steps, docs/RESULTS.md), the PPO sizes for a 2-core CPU host (the host
plan scales them), and under ``gradient`` what changes for ``bptt``/``shac``. Tasks not listed use
:func:`task_defaults`' base row. The CLI, ``make_env`` users (README), eval and the host plan read it."""


def task_defaults(task: str, algo: str | None = None) -> dict[str, Any]:
    """The defaults of ``task`` for ``algo`` (``None``: the task's own algorithm), ``gradient`` applied
    for ``bptt``/``shac``; without the ``gradient`` entry."""
    row = dict(TASK_DEFAULTS.get(task, _BASE))
    gradient = row.pop("gradient")
    if (algo or row["algo"]) in ("bptt", "shac"):
        row.update(gradient)
    if algo is not None:
        row["algo"] = algo
    return row


def default_ppo(task: str) -> str:
    """The task's PPO trainer: its default algorithm when that is a PPO, else ``sb3-ppo``."""
    algo = TASK_DEFAULTS.get(task, _BASE)["algo"]
    return algo if algo in PPO_ALGOS else "sb3-ppo"


def parse_override(item: str) -> tuple[str, Any]:
    """``"key=value"`` -> ``(key, value)``; the value is read as JSON when it parses, else a string.

    ``max_episode_steps=64`` gives an int, ``cameras=["depth"]`` a list, ``scene=gen:pillars`` a string.
    """
    key, sep, raw = item.partition("=")
    key = key.strip()
    if not sep or not key.isidentifier():
        raise ConfigError(f"--set {item!r} must look like KEY=VALUE with KEY a Python identifier, e.g. --set max_episode_steps=64")
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    return key, value


@dataclass
class TrainConfig:
    """Everything a training run needs; saved as ``config.json`` in the run folder.

    Attributes:
        task: registered task name (``navigation``, ``hover``, ...).
        timesteps: total env steps (all envs together).
        num_envs: parallel agents.
        workers: local scene workers to spawn (``None``: the env's default).
        connect: Zenoh endpoints of a router or remote workers.
        run_id: key namespace of the run (``None``: random).
        backend: renderer of local workers (``auto``, ``egl``, ``raycast``; ``None``: env default).
        seed: seed of the env, the policy initialisation and PPO's sampling.
        out: run folder; ``None``: ``runs/TASK-<timestamp>``.
        device: torch device of the policy; ``auto``: CUDA when torch sees a GPU, else the CPU.
        worker_threads: tracing threads of each local worker (``None``: the host plan's share).
        host_plan: the host plan the run was sized with (written by the trainer, for the record).
        threads: torch CPU threads of the training process while it steps the env (the scene
            workers use the other cores).
        update_threads: threads of a PPO update, when the local workers sit idle (plain PPO on
            CPU only): each minibatch is split across them, one torch thread each; ``None``: every
            CPU this process may use or one thread, whichever the run's updates were timed faster
            with (re-timed after 8 updates, then less and less often).
        n_steps: rollout length per env between updates.
        batch_size: PPO minibatch size.
        lr: Adam learning rate (``None``: 3e-4, or the task's for ``bptt``/``shac``).
        n_epochs: passes over each rollout.
        gamma: discount.
        gae_lambda: GAE lambda.
        ent_coef: entropy bonus.
        clip_range: PPO clip range.
        log_std_init: initial log standard deviation of the policy's Gaussian action noise (actions
            are clipped to [-1, 1]); ``None``: the task's default.
        checkpoint_every: save a checkpoint every this many env steps (0: only the final model).
        video_every: film one deterministic episode every this many env steps, in the background
            (``RUN/videos/step-<n>.gif`` and TensorBoard; :mod:`visfly_dist.training.training_video`); 0: never;
            ``None``: the host plan's (every tenth of the run from 8 cores, else never).
        backbone: image backbone of the extractor.
        normalize: running normalisation of vector observations and of rewards (VecNormalize).
        progress: print progress lines.
        overlap: collect the next rollout while PPO updates on the last one (policy lag of one
            update, see :mod:`visfly_dist.training.overlap`). ``None``: on when every scene worker
            is remote (``workers=0``), where the learner would otherwise sit idle through one
            network round trip per step (20 ms away: 0.96 of the 0 ms loop against 0.78 without);
            off with local workers, which need the cores the overlapped update would take. The lag
            can cost sample efficiency: on hover (20k steps, short rollouts) it cost most of what
            PPO learned; navigation results are in docs/RESULTS.md.
        scene_roots: folders scene files may be loaded from (``--scene-root``); ``scenes`` paths
            must lie under one of them.
        overrides: extra keyword arguments of ``make_env`` (``--set key=value``).
        algo: ``ppo`` (the tensor PPO), ``sb3-ppo`` (SB3's loop), or ``bptt`` / ``shac`` (differentiable, through the dynamics; they use
            ``lr``, ``gamma``, ``horizon``, and SHAC's critic ``gae_lambda``, ``n_epochs``, ``batch_size``);
            ``None``: the task's (``TASK_DEFAULTS``).
        horizon: BPTT/SHAC window length, steps (the graph is cut between windows; ``None``: 32 or the task's).
        recurrent: an LSTM between the extractor and the heads (sb3-contrib ``RecurrentPPO``; see
            :mod:`visfly_dist.training.ppo`); PPO only.
    """

    task: str
    timesteps: int | None = None
    num_envs: int | None = None
    workers: int | None = None
    connect: tuple[str, ...] = ()
    run_id: str | None = None
    backend: str | None = None
    seed: int = 0
    out: str | None = None
    device: str = "auto"
    worker_threads: int | None = None
    threads: int = 1
    update_threads: int | None = None
    n_steps: int | None = None
    batch_size: int | None = None
    lr: float | None = None
    n_epochs: int | None = None
    gamma: float = 0.99
    gae_lambda: float = 0.95
    ent_coef: float = 0.0
    clip_range: float = 0.2
    log_std_init: float | None = None
    checkpoint_every: int = 50_000
    video_every: int | None = None
    backbone: str = "visfly-cnn"
    normalize: bool = True
    progress: bool = True
    overlap: bool | None = None
    scene_roots: tuple[str, ...] = ()
    overrides: dict[str, Any] = field(default_factory=dict)
    algo: str | None = None
    horizon: int | None = None
    recurrent: bool = False
    host_plan: dict[str, Any] = field(default_factory=dict)

    def resolved(self) -> "TrainConfig":
        """A copy with the algorithm and the task's defaults for it filled in, and ``out`` set."""
        defaults = task_defaults(self.task, self.algo)
        algo = defaults.pop("algo")
        filled = {k: v for k, v in defaults.items() if getattr(self, k) is None}
        overlap = self.overlap if self.overlap is not None else (algo in PPO_ALGOS and self.workers == 0)
        video_every = 0 if self.video_every is None else self.video_every
        cfg = replace(self, connect=tuple(self.connect), scene_roots=tuple(self.scene_roots),
                      overrides=dict(self.overrides), algo=algo, overlap=overlap, video_every=video_every,
                      host_plan=dict(self.host_plan), **filled)
        if cfg.out is None:
            cfg.out = str(Path("runs") / f"{self.task}-{time.strftime('%Y%m%d-%H%M%S')}")
        return cfg

    def size_problems(self) -> list[str]:
        """Problems with the sizes given (those left ``None`` are the host plan's to choose): checked
        before the plan reads them, so a bad flag fails before any choice is made or printed."""
        return [f"{name}={value!r} must be an int >= {low}" for name, low in _SIZES
                if (value := getattr(self, name)) is not None and not _int_at_least(value, low)]

    def problems(self) -> list[str]:
        """Every problem with this (resolved) config, as messages (empty when valid)."""
        out: list[str] = []
        for name, low in (*_SIZES, ("n_epochs", 1), ("checkpoint_every", 0), ("threads", 1)):
            value = getattr(self, name)
            if not _int_at_least(value, low):
                out.append(f"{name}={value!r} must be an int >= {low}")
        if self.worker_threads is not None and (not isinstance(self.worker_threads, int) or self.worker_threads < 1):
            out.append(f"worker_threads={self.worker_threads!r} must be an int >= 1")
        if self.workers is not None and (not isinstance(self.workers, int) or self.workers < 0):
            out.append(f"workers={self.workers!r} must be an int >= 0")
        if self.update_threads is not None and (not isinstance(self.update_threads, int)
                                                or isinstance(self.update_threads, bool) or self.update_threads < 1):
            out.append(f"update_threads={self.update_threads!r} must be an int >= 1 or None (timed choice)")
        if _int_at_least(self.n_steps, 1) and _int_at_least(self.num_envs, 1) and _int_at_least(self.batch_size, 2):
            if self.batch_size > self.n_steps * self.num_envs:
                out.append(
                    f"batch_size={self.batch_size} must be <= n_steps * num_envs = {self.n_steps * self.num_envs}; "
                    "lower --batch-size or raise --n-steps / --num-envs"
                )
        if not isinstance(self.seed, int) or self.seed < 0:
            out.append(f"seed={self.seed!r} must be an int >= 0")
        if self.lr is None or not 0 < float(self.lr) < 1:  # None before resolved()
            out.append(f"lr={self.lr!r} must be in (0, 1)")
        for name in ("gamma", "gae_lambda"):
            if not 0 < float(getattr(self, name)) <= 1:
                out.append(f"{name}={getattr(self, name)!r} must be in (0, 1]")
        if self.log_std_init is not None and (isinstance(self.log_std_init, bool) or not isinstance(self.log_std_init, (int, float))
                                              or not -5.0 <= self.log_std_init <= 2.0):
            out.append(f"log_std_init={self.log_std_init!r} must be a number in [-5, 2] (std = exp of it)")
        if self.algo not in ALGOS:
            out.append(f"algo={self.algo!r} must be one of {ALGOS}")
        if not isinstance(self.horizon, int) or isinstance(self.horizon, bool) or self.horizon < 1:
            out.append(f"horizon={self.horizon!r} must be an int >= 1")
        if self.recurrent and self.algo in ("bptt", "shac"):
            out.append(f"recurrent=True is for PPO; {self.algo} differentiates through the dynamics over its horizon "
                       "and has no recurrent actor: drop --recurrent or use --algo sb3-ppo")
        if self.backbone not in BACKBONES:
            out.append(f"backbone={self.backbone!r} must be one of {BACKBONES}")
        return out + self._owned_setting_problems() + self._out_problems() + self._scene_problems()

    def _out_problems(self) -> list[str]:
        """An ``--out`` that holds a run already (its model would be overwritten) or cannot be made."""
        if self.out is None:
            return []
        out = Path(self.out)
        if (out / "config.json").exists():
            return [f"--out {str(out)!r} holds a run already (its config.json); give another folder, or remove "
                    "that one, so that its model is not overwritten"]
        existing = next((p for p in (out, *out.parents) if p.exists()), None)
        if existing is not None and not existing.is_dir():
            return [f"--out {str(out)!r}: {str(existing)!r} is not a folder"]
        if existing is not None and not os.access(existing, os.W_OK | os.X_OK):
            return [f"--out {str(out)!r}: cannot write in {str(existing)!r}"]
        return []

    def _owned_setting_problems(self) -> list[str]:
        """``--set`` keys that a flag or the trainer sets (``make_env`` would get them twice)."""
        owners = {"num_envs": "--num-envs", "seed": "--seed", "requires_grad": "the trainer (bptt and shac set it)"}
        return [f"--set {key}=... is not taken here: {owner} sets it" for key, owner in owners.items()
                if key in self.overrides]

    def _scene_problems(self) -> list[str]:
        """Missing ``--scene-root`` folders, and scene paths outside every root."""
        from visfly_dist.aggregator.dataset import expand_sources

        out = [f"--scene-root {r!r} is not a folder" for r in self.scene_roots if not Path(r).is_dir()]
        scenes = self.overrides.get("scenes", ())
        scenes = (scenes,) if isinstance(scenes, str) else tuple(scenes)
        paths = tuple(str(s) for s in scenes if not str(s).startswith("gen:"))
        if paths and not out:
            try:
                expand_sources(paths, tuple(self.scene_roots))
            except ConfigError as exc:
                out.append(f"{exc} (roots come from --scene-root DIR; e.g. --scene-root . for scenes in this folder)")
        return out

    def validate(self) -> "TrainConfig":
        """Raise ConfigError listing every problem; return self when valid."""
        problems = self.problems()
        if problems:
            raise ConfigError("invalid training config: " + "; ".join(problems))
        return self

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["connect"] = list(self.connect)
        d["scene_roots"] = list(self.scene_roots)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "TrainConfig":
        """Inverse of :meth:`to_dict`; unknown keys raise ConfigError."""
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise ConfigError(f"training config has unknown keys {sorted(unknown)}; accepted: {sorted(cls.__dataclass_fields__)}")
        return cls(**{**d, "connect": tuple(d.get("connect", ())), "scene_roots": tuple(d.get("scene_roots", ()))})
