"""Task-independent environment settings, as one typed dataclass with one ``validate()``.

Tasks subclass :class:`EnvConfig` to add their own fields and defaults (see ``visfly_dist.tasks``).
Derived values (``num_scenes``, the aggregator's configs) are computed here, in one place.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, Mapping, Optional, Sequence

import torch

from visfly_dist.aggregator.config import PoolConfig, SceneSetConfig
from visfly_dist.aggregator.dataset import expand_sources
from visfly_dist.client.noise import NoiseSpec
from visfly_dist.dynamics.airframe import load_airframe
from visfly_dist.dynamics.config import DynamicsConfig
from visfly_dist.errors import ConfigError
from visfly_dist.protocol.cameras import CameraSpec

STATE_NOISE_KEY = "state"

_DYNAMICS_DEFAULTS: dict[str, Any] = {f.name: f.default for f in fields(DynamicsConfig)}
"""Defaults of the dynamics settings the env shares, read from ``DynamicsConfig``: set there only."""


def _default_pool() -> PoolConfig:
    return PoolConfig(num_local_workers=2, backend="raycast")


@dataclass
class EnvConfig:
    """Settings every task shares.

    Attributes:
        num_envs: agents in the batch (= ``num_scenes * agents_per_scene``).
        scenes: scene sources: paths or globs under ``pool.scene_roots``, or ``gen:KIND?k=v``.
        agents_per_scene: agents flying in one scene (a team when ``multi_agent``).
        swap_every_resets: replace a scene after this many episode resets in it (0 = never).
        shuffle_scenes: draw sources in a shuffled order.
        controller: action interface: ``ctbr`` (thrust + body rates), ``srt``, ``lv`` or ``ps``.
        sim_dt: physics substep, seconds.
        ctrl_dt: control period (one env step), seconds; a multiple of ``sim_dt``.
        integrator: ``rk4`` or ``euler``.
        action_delay_s: command latency (a FIFO of actions), seconds.
        motor_lag: first-order lag on rotor speeds (False: rotors reach their command at once).
        wind: constant world-frame wind, m/s: None, ``(x, y, z)`` for every agent, or one triple per agent.
        ground: apply the ground reaction at ``z = 0``.
        compile: run the control step through ``torch.compile``.

    The dynamics settings (``controller`` to ``compile``) take their defaults from
    :class:`~visfly_dist.dynamics.config.DynamicsConfig` (e.g. ``ctrl_dt`` 0.03 s, 33.3 Hz) and reach
    it whole through :meth:`dynamics_config`: every field of this class named as one of its fields.
        airframe: airframe name or JSON path for ``load_airframe``.
        cameras: the sensors mounted on every drone (may be empty).
        noise: per sensor (a camera name or ``"state"``) the noise models applied in order.
        max_episode_steps: episode length limit (a truncation).
        device: torch device of the dynamics and the observations.
        requires_grad: keep the autograd graph through the dynamics (BPTT); images are constants.
        seed: seed of spawns, noise and scene order.
        pool: where scene workers come from (local processes and/or remote endpoints).
        multi_agent: agents of one scene see each other in images (workers render the others).
        drone_radius: collision radius of a drone, metres.
        search_radius: nearest-obstacle queries look this far, metres.
        lost_hold_s: how long an agent whose worker failed is held (paused, no transition) while
            the worker is replaced, before its episode ends as truncated (``lost``); 0 cuts at once.
    """

    evaluation_defaults: ClassVar[dict[str, Any]] = {}
    """Settings ``visfly-dist eval`` applies over the training run's (e.g. a task's training
    curriculum turned off); the evaluation's own ``--set`` still wins."""

    num_envs: int = 16
    scenes: tuple[str, ...] = ("gen:empty",)
    agents_per_scene: int = 1
    swap_every_resets: int = 0
    shuffle_scenes: bool = True
    controller: str = _DYNAMICS_DEFAULTS["controller"]
    sim_dt: float = _DYNAMICS_DEFAULTS["sim_dt"]
    ctrl_dt: float = _DYNAMICS_DEFAULTS["ctrl_dt"]
    integrator: str = _DYNAMICS_DEFAULTS["integrator"]
    action_delay_s: float = _DYNAMICS_DEFAULTS["action_delay_s"]
    motor_lag: bool = _DYNAMICS_DEFAULTS["motor_lag"]
    wind: Optional[tuple] = _DYNAMICS_DEFAULTS["wind"]
    ground: bool = _DYNAMICS_DEFAULTS["ground"]
    compile: bool = _DYNAMICS_DEFAULTS["compile"]
    airframe: str = "visfly"
    cameras: tuple[CameraSpec, ...] = ()
    noise: Mapping[str, Sequence[NoiseSpec]] = field(default_factory=dict)
    max_episode_steps: int = 256
    device: str = "cpu"
    requires_grad: bool = False
    seed: int = 0
    pool: PoolConfig = field(default_factory=_default_pool)
    multi_agent: bool = False
    drone_radius: float = 0.1
    search_radius: float = 5.0
    lost_hold_s: float = 30.0

    def __post_init__(self) -> None:
        if isinstance(self.scenes, str):
            self.scenes = (self.scenes,)
        self.scenes = tuple(self.scenes)
        self.cameras = tuple(self.cameras)
        self.noise = {k: tuple(v) for k, v in dict(self.noise).items()}
        if isinstance(self.wind, list):  # e.g. from JSON (``--set wind=[1,0,0]``)
            self.wind = tuple(tuple(w) if isinstance(w, list) else w for w in self.wind)

    @property
    def num_scenes(self) -> int:
        """Scenes loaded at once."""
        return self.num_envs // self.agents_per_scene

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))

    def problems(self) -> list[str]:
        """Every problem with this config, as messages (empty when valid). Subclasses extend it."""
        out: list[str] = []
        for name, low in (("num_envs", 1), ("agents_per_scene", 1), ("max_episode_steps", 1)):
            value = getattr(self, name)
            if not _is_int(value) or value < low:
                out.append(f"{name}={value!r} must be an int >= {low}")
        counts_ok = not out
        if counts_ok and self.num_envs % self.agents_per_scene:
            out.append(f"num_envs={self.num_envs!r} must be divisible by agents_per_scene={self.agents_per_scene!r}")
        out += self._dynamics_problems()
        if not _is_number(self.lost_hold_s) or not 0 <= self.lost_hold_s <= 3600:
            out.append(f"lost_hold_s={self.lost_hold_s!r} must be a number of seconds in [0, 3600]")
        for name in ("drone_radius", "search_radius"):
            value = getattr(self, name)
            if not _is_number(value) or not 0 < value <= 100:
                out.append(f"{name}={value!r} must be a number of metres in (0, 100]")
        try:
            torch.device(self.device)
        except (RuntimeError, TypeError):
            out.append(f"device={self.device!r} is not a torch device (e.g. 'cpu', 'cuda:0')")
        out += self._sensor_problems()
        if not isinstance(self.pool, PoolConfig):
            out.append(f"pool must be a PoolConfig, got {type(self.pool).__name__}")
            return out
        out += [f"pool: {p}" for p in self.pool.problems()]
        scene_set = self.scene_set() if counts_ok else dataclasses.replace(self.scene_set(num_scenes=1), agents_per_scene=1)
        out += scene_set.problems()
        if not scene_set.problems():
            try:
                expand_sources(scene_set.sources, self.pool.scene_roots)
            except ConfigError as exc:
                out.append(str(exc))
        return out

    def _dynamics_problems(self) -> list[str]:
        out = []
        for name in ("sim_dt", "ctrl_dt", "action_delay_s"):
            value = getattr(self, name)
            if not _is_number(value) or not 0 <= value <= 1:
                out.append(f"{name}={value!r} must be a number of seconds in [0, 1]")
        for name in ("motor_lag", "ground", "compile"):
            if not isinstance(getattr(self, name), bool):
                out.append(f"{name}={getattr(self, name)!r} must be True or False")
        if self.wind is not None:
            try:
                torch.as_tensor(self.wind, dtype=torch.float64)
            except (TypeError, ValueError, RuntimeError):
                out.append(f"wind={self.wind!r} must be None, (x, y, z) m/s, or one such triple per agent")
        if not out:
            try:
                self.dynamics_config()
            except ConfigError as exc:
                out.append(str(exc))
        try:
            load_airframe(self.airframe)
        except (ConfigError, OSError) as exc:
            out.append(f"airframe={self.airframe!r}: {exc}")
        return out

    def _sensor_problems(self) -> list[str]:
        out = []
        cams = [c for c in self.cameras if isinstance(c, CameraSpec)]
        if len(cams) != len(self.cameras):
            out.append("cameras must be CameraSpec instances")
        names = [c.name for c in cams]
        if len(set(names)) != len(names):
            out.append(f"camera names {names} must be unique")
        if STATE_NOISE_KEY in names:
            out.append(f"camera name {STATE_NOISE_KEY!r} is reserved for the state sensor; rename the camera")
        kinds = {c.name: c.kind for c in cams}
        for sensor, specs in self.noise.items():
            if sensor != STATE_NOISE_KEY and sensor not in kinds:
                out.append(f"noise for unknown sensor {sensor!r}; valid: {[STATE_NOISE_KEY, *names]}")
                continue
            for spec in specs:
                if not isinstance(spec, NoiseSpec):
                    out.append(f"noise[{sensor!r}] entries must be NoiseSpec, got {type(spec).__name__}")
                else:
                    out += [f"noise[{sensor!r}]: {p}" for p in spec.problems(kinds.get(sensor, STATE_NOISE_KEY))]
        return out

    def validate(self) -> "EnvConfig":
        """Raise ConfigError listing every problem; return self when valid."""
        problems = self.problems()
        if problems:
            raise ConfigError(f"invalid {type(self).__name__}: " + "; ".join(problems))
        return self

    def dynamics_config(self) -> DynamicsConfig:
        """The dynamics settings of this config: every ``DynamicsConfig`` field this class also has,
        by name (raises ConfigError when invalid)."""
        return DynamicsConfig(**{name: getattr(self, name) for name in self.dynamics_field_names()})

    @classmethod
    def dynamics_field_names(cls) -> tuple[str, ...]:
        """The fields of this config that are ``DynamicsConfig`` settings (passed on by ``dynamics_config``)."""
        own = set(cls.field_names())
        return tuple(name for name in _DYNAMICS_DEFAULTS if name in own)

    def scene_set(self, num_scenes: int | None = None) -> SceneSetConfig:
        """The aggregator's scene-set config derived from this one."""
        return SceneSetConfig(sources=self.scenes, num_scenes=self.num_scenes if num_scenes is None else num_scenes,
                              agents_per_scene=self.agents_per_scene, swap_every_resets=self.swap_every_resets,
                              shuffle=self.shuffle_scenes, seed=self.seed)

    def replace(self, **changes: Any) -> "EnvConfig":
        """A copy with some fields changed; unknown names raise ConfigError naming them."""
        unknown = sorted(set(changes) - set(self.field_names()))
        if unknown:
            raise ConfigError(f"unknown {type(self).__name__} settings {unknown}; valid: {sorted(self.field_names())}")
        return dataclasses.replace(self, **changes)


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)
