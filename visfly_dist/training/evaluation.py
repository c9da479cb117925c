"""Evaluating a trained policy: success with a confidence interval, end causes, returns, and a video.

Episodes are counted per agent up to a quota of ``ceil(episodes / num_envs)`` each, so that short
(often failed) episodes do not crowd out long ones; the first ``episodes`` counted are reported.
In team tasks (``team_size`` agents per scene, whose episodes end together) an episode is a team's:
it succeeds when every member does, its end cause is its members' first in ``END_CAUSES`` order
(a collision, say, rather than the teammates' ``swapped``), its return is the members' mean.
Returns are the env's raw rewards (``info["episode"]`` of ``VecMonitor``), never the normalised ones.
Each episode's end cause comes from :func:`visfly_dist.tasks.outcomes.end_cause`; the scene it
flew in is the concrete source of its scene slot (a seeded ``gen:`` spec or a root-relative path).
A recurrent policy (``train --recurrent``: an sb3-contrib ``RecurrentPPO`` checkpoint, recognised from
the zip) carries its LSTM state from step to step, per agent, zeroed where that agent's episode starts.
"""

from __future__ import annotations

import json
import math
import zipfile
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeGuard

import numpy as np
from stable_baselines3 import PPO
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.vec_env import VecEnv, VecMonitor, VecNormalize

from visfly_dist.client.env_base import DroneEnvBase
from visfly_dist.errors import ConfigError
from visfly_dist.tasks import make_env, task_class
from visfly_dist.tasks.outcomes import END_CAUSES, end_cause
from visfly_dist.training.checkpoints import load_normalization, norm_path
from visfly_dist.training.config import TrainConfig
from visfly_dist.training.run import env_kwargs
from visfly_dist.training.video import VideoRecorder


class Policy(Protocol):
    """What :func:`evaluate` runs: anything with SB3's ``predict`` (an SB3 model, a BPTT/SHAC
    :class:`~visfly_dist.training.diff_common.DiffActor`)."""

    def predict(self, observation: dict[str, np.ndarray], /, *,
                deterministic: bool = ...) -> tuple[np.ndarray, object]: ...


class RecurrentPolicy(Protocol):
    """A policy whose ``predict`` takes and returns its state (SB3's recurrent models)."""

    def predict(self, observation: dict[str, np.ndarray], state: tuple[np.ndarray, ...] | None = ...,
                episode_start: np.ndarray | None = ...,
                deterministic: bool = ...) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]: ...


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval of a success rate (95 % with the default ``z``); ``(0, 1)`` when ``n == 0``."""
    if n <= 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


@dataclass
class Episode:
    """One evaluated episode: agent index (team tasks: the team's first agent), scene source, outcome,
    return (team tasks: the members' mean) and length."""

    agent: int
    scene: str
    success: bool
    end_cause: str
    episode_return: float
    length: int


@dataclass
class EvalStats:
    """Outcome of an evaluation in one mode.

    Attributes:
        mode: ``deterministic`` (mean action) or ``sampled`` (actions drawn from the policy).
        seed: the env seed of the evaluation.
        episodes: episodes counted.
        success_rate: share of episodes ending in success.
        success_ci95: Wilson 95 % interval of the success rate.
        mean_return: mean undiscounted return.
        mean_length: mean episode length, steps.
        end_causes: episodes per end cause (every cause of ``END_CAUSES``, zeros included).
        scenes: the distinct scene sources the episodes flew in.
        team_size: agents per counted episode (1, or the team of a team task).
        video_frames: frames written to the video (0 without one).
        video_episode_length: length of the filmed episode, steps (0 without a video).
        video_success: whether the filmed episode succeeded.
        episode_log: every episode.
    """

    mode: str
    seed: int
    episodes: int
    success_rate: float
    success_ci95: tuple[float, float]
    mean_return: float
    mean_length: float
    end_causes: dict[str, int]
    scenes: list[str]
    team_size: int = 1
    video_frames: int = 0
    video_episode_length: int = 0
    video_success: bool = False
    episode_log: list[Episode] = field(default_factory=list)

    @property
    def collisions(self) -> int:
        return self.end_causes["collision"]

    @property
    def out_of_bounds(self) -> int:
        return self.end_causes["out_of_bounds"]

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def line(self) -> str:
        """One summary line: success with its interval, causes, return and length."""
        lo, hi = self.success_ci95
        causes = "  ".join(f"{k} {v}" for k, v in self.end_causes.items() if v)
        teams = f" teams of {self.team_size}" if self.team_size > 1 else ""
        return (f"{self.mode:>13}: success {self.success_rate:.2f} [{lo:.2f}, {hi:.2f}] over {self.episodes}{teams}  "
                f"return {self.mean_return:8.2f}  length {self.mean_length:6.1f}  ends: {causes}")


def find_run_config(checkpoint: Path) -> TrainConfig | None:
    """The ``config.json`` of the run a checkpoint belongs to (its folder or the one above), if any."""
    for folder in (checkpoint.parent, checkpoint.parent.parent):
        path = folder / "config.json"
        if path.is_file():
            return TrainConfig.from_dict(json.loads(path.read_text()))
    return None


def missing_normalization(checkpoint: Path, run_cfg: TrainConfig | None) -> str | None:
    """Why ``checkpoint`` (a PPO ``.zip``) cannot be evaluated as it is, or ``None``: its run trained
    on normalised observations and its ``NAME.norm.npz`` is not beside it (the policy would act, without
    a word, on values it never saw). Raises ConfigError for that; returns a warning when the run's
    ``config.json`` is not found either, so nothing says whether it normalised."""
    stats = norm_path(checkpoint)
    if stats.is_file():
        return None
    if run_cfg is None:
        return (f"no {stats.name} and no run config.json beside {str(checkpoint)!r}: evaluating without observation "
                "normalisation, as for a run trained with --no-normalize")
    if run_cfg.normalize:
        raise ConfigError(f"{str(stats)!r} is missing: the run trained on normalised observations (config.json: "
                          f"normalize true), and its policy without those statistics acts on values it never saw; put "
                          f"the {stats.name} written with the checkpoint beside it")
    return None


def is_recurrent_checkpoint(checkpoint: Path) -> bool:
    """Whether ``checkpoint`` (an SB3 ``.zip``) holds an sb3-contrib recurrent policy (``RecurrentPPO``):
    read from the policy class recorded in the zip, without unpickling anything."""
    try:
        with zipfile.ZipFile(checkpoint) as z:
            data = json.loads(z.read("data"))
    except (zipfile.BadZipFile, KeyError, ValueError) as exc:
        raise ConfigError(f"checkpoint {checkpoint} is not a model .zip written by 'visfly-dist train' ({exc})") from exc
    policy_class = data.get("policy_class")
    module = policy_class.get("__module__", "") if isinstance(policy_class, dict) else ""
    return module.startswith("sb3_contrib.common.recurrent")


def is_recurrent(model: object) -> TypeGuard[RecurrentPolicy]:
    """Whether ``model`` (an SB3 model) has a recurrent policy, whose ``predict`` takes and returns a state."""
    return hasattr(getattr(model, "policy", None), "lstm_actor")


def load_policy(checkpoint: Path, env: VecEnv, device: str = "cpu") -> tuple[OnPolicyAlgorithm, VecEnv]:
    """Load a PPO (or, recognised from the zip, RecurrentPPO) checkpoint for ``env``; wraps ``env`` in
    its saved normalisation when there is one."""
    if not checkpoint.is_file():
        raise ConfigError(f"checkpoint {str(checkpoint)!r} does not exist; pass a .zip written by 'visfly-dist train'")
    stats = norm_path(checkpoint)
    if stats.is_file():
        env = load_normalization(env, stats)
    cls: type[OnPolicyAlgorithm] = PPO
    if is_recurrent_checkpoint(checkpoint):
        from sb3_contrib import RecurrentPPO

        cls = RecurrentPPO
    try:
        model = cls.load(checkpoint, env=env, device=device)
    except ValueError as exc:
        raise ConfigError(f"checkpoint {checkpoint} does not fit this env ({exc}); evaluate with the training's task and --set settings") from exc  # noqa: E501
    return model, env


def _episode(members: list[int], infos: list[dict[str, Any]], scene: str, team: int, limit: int) -> Episode:
    """The counted episode of the agents ``members`` (one agent, or the members of a team that ended)."""
    lengths = [int(infos[i]["episode"]["l"]) for i in members]
    causes = [end_cause(infos[i], length, limit) for i, length in zip(members, lengths)]
    return Episode(agent=members[0], scene=scene,
                   success=len(members) == team and all(bool(infos[i].get("is_success")) for i in members),
                   end_cause=min(causes, key=END_CAUSES.index),
                   episode_return=float(np.mean([infos[i]["episode"]["r"] for i in members])), length=max(lengths))


def evaluate(model: Policy, env: VecEnv, episodes: int, deterministic: bool = True, seed: int = 0,
             recorder: VideoRecorder | None = None, film_success: bool = False) -> EvalStats:
    """Run ``model`` on ``env`` (reseeded with ``seed``) until ``episodes`` episodes are counted.

    Args:
        model: the policy; a recurrent one (:func:`is_recurrent`) gets its state back each step,
            zeroed for the agents whose episode starts (all of them after the reset).
        env: the (possibly normalising) VecEnv the model was loaded with.
        episodes: episodes to count (>= 1).
        deterministic: take the mean action instead of sampling.
        seed: env seed (spawns, noise); the same seed gives both modes the same starts.
        recorder: when given, films agent ``recorder.agent``: one frame per observation it acts on,
            so the video has as many frames as the filmed episode has steps.
        film_success: film agent ``recorder.agent``'s episodes until one succeeds (the last whole
            one is kept when none does before the evaluation ends); otherwise its first episode.
    """
    if episodes < 1:
        raise ConfigError(f"episodes={episodes!r} must be >= 1")
    base = env.unwrapped
    assert isinstance(base, DroneEnvBase)  # every task's env
    team = int(getattr(base, "team_size", 1))
    n, limit = env.num_envs, int(base.config.max_episode_steps)
    quota = math.ceil(episodes / (n // team))
    counted = np.zeros(n // team, dtype=np.int64)
    log: list[Episode] = []
    filming, filmed_length, filmed_success = recorder, 0, False  # filming: the recorder while it films
    last_failure: list[np.ndarray] = []
    env.seed(seed)
    obs = env.reset()
    recurrent, state, starts = model if is_recurrent(model) else None, None, np.ones(n, dtype=bool)
    step, ret = 0, 0.0
    while len(log) < episodes:
        assert isinstance(obs, dict)  # every task's observation space is a Dict
        if filming is not None:
            filming.add(obs, f"step {step}  return {ret:.2f}")
        sources = base.aggregator.agent_sources()  # the scene of each agent's running episode
        if recurrent is not None:
            actions, state = recurrent.predict(obs, state=state, episode_start=starts, deterministic=deterministic)
        else:
            actions, _ = model.predict(obs, deterministic=deterministic)
        obs, rewards, dones, infos = env.step(actions)
        starts = np.asarray(dones, dtype=bool)
        if filming is not None:
            raw = env.get_original_reward() if isinstance(env, VecNormalize) else rewards
            step, ret = step + 1, ret + float(raw[filming.agent])
        for i in np.flatnonzero(dones):
            info, ep = infos[i], infos[i]["episode"]
            if filming is not None and i == filming.agent:
                filmed_length, filmed_success = int(ep["l"]), bool(info.get("is_success"))
                if filmed_success or not film_success:
                    filming = None
                else:
                    last_failure, filming.frames = filming.frames, []
                    step, ret = 0, 0.0
        for unit in np.unique(np.flatnonzero(dones) // team):
            if counted[unit] < quota and len(log) < episodes:
                counted[unit] += 1
                members = [i for i in range(unit * team, (unit + 1) * team) if dones[i]]
                log.append(_episode(members, infos, sources[members[0]], team, limit))
    if filming is not None and film_success and last_failure:
        filming.frames = last_failure  # no success filmed: keep the last whole episode
    wins = sum(e.success for e in log)
    causes = Counter(e.end_cause for e in log)
    return EvalStats(
        mode="deterministic" if deterministic else "sampled",
        seed=seed,
        episodes=len(log),
        success_rate=wins / len(log),
        success_ci95=wilson_interval(wins, len(log)),
        mean_return=float(np.mean([e.episode_return for e in log])),
        mean_length=float(np.mean([e.length for e in log])),
        end_causes={c: causes.get(c, 0) for c in END_CAUSES},
        scenes=sorted({e.scene for e in log}),
        team_size=team,
        video_frames=len(recorder.frames) if recorder is not None else 0,
        video_episode_length=filmed_length,
        video_success=filmed_success,
        episode_log=log,
    )


def eval_config(task: str, seed: int, run_cfg: TrainConfig | None, overrides: dict[str, Any],
                pool: dict[str, Any]) -> TrainConfig:
    """The training run's settings (when known) with the evaluation's seed, the task's
    ``evaluation_defaults`` and the given changes (which win)."""
    cfg = run_cfg if run_cfg is not None and run_cfg.task == task else TrainConfig(task=task)
    cfg = cfg.resolved()
    cfg.out = None  # the training run's folder: evaluation writes nothing there
    cfg.seed = seed
    cfg.worker_threads = None  # this host's cores, shared among the workers (the run's host may have had more)
    cfg.overrides = {**cfg.overrides, **task_class(task).config_class.evaluation_defaults, **overrides}
    for key, value in pool.items():
        if value is not None:
            setattr(cfg, key, value)
    return cfg.validate()


def build_eval_env(task: str, num_envs: int | None, seed: int, run_cfg: TrainConfig | None,
                   overrides: dict[str, Any], pool: dict[str, Any]) -> VecEnv:
    """``make_env`` with the training run's settings (when known), then the given changes."""
    cfg = eval_config(task, seed, run_cfg, overrides, pool)
    return VecMonitor(make_env(task, num_envs=cfg.num_envs if num_envs is None else num_envs, **env_kwargs(cfg)))
