"""``make_env``: build a task's vector env by name, with settings overridden by keyword."""

from __future__ import annotations

import importlib
from typing import Any, Iterable

from visfly_dist.client.config import EnvConfig
from visfly_dist.client.env_base import DroneEnvBase
from visfly_dist.errors import ConfigError

TASKS: dict[str, str] = {
    "navigation": "visfly_dist.tasks.navigation:NavigationEnv",
    "hover": "visfly_dist.tasks.hover:HoverEnv",
    "landing": "visfly_dist.tasks.landing:LandingEnv",
    "gap_crossing": "visfly_dist.tasks.gap_crossing:GapCrossingEnv",
    "racing": "visfly_dist.tasks.racing:RacingEnv",
    "tracking": "visfly_dist.tasks.tracking:TrackingEnv",
    "navigation_moving": "visfly_dist.tasks.navigation_moving:MovingNavigationEnv",
}
"""Task name -> ``module:EnvClass``."""


def task_class(name: str) -> type[DroneEnvBase]:
    """The env class of task ``name``; ConfigError listing the valid names otherwise."""
    if name not in TASKS:
        raise ConfigError(f"unknown task {name!r}; valid tasks: {', '.join(TASKS)}")
    module, cls = TASKS[name].split(":")
    return getattr(importlib.import_module(module), cls)


def make_env(name: str, num_envs: int | None = None, **overrides: Any) -> DroneEnvBase:
    """Build task ``name`` as an SB3 ``VecEnv`` (workers are started; close it when done).

    Args:
        name: one of :data:`TASKS`.
        num_envs: agents in the batch (default: the task's).
        overrides: any field of the task's config class (e.g. ``cameras=()``, ``seed=3``,
            ``pool=PoolConfig(num_local_workers=1)``).

    Raises:
        ConfigError: unknown task or setting, or an invalid config (every problem listed).
    """
    return task_class(name)(task_config(name, num_envs, **overrides))


def task_config(name: str, num_envs: int | None = None, **overrides: Any) -> EnvConfig:
    """The config :func:`make_env` would build task ``name`` from, validated, with nothing started:
    a caller that reports progress checks the settings before it says it is starting anything.

    Raises:
        ConfigError: as :func:`make_env`.
    """
    check_setting_names(name, overrides)
    if num_envs is not None:
        overrides["num_envs"] = num_envs
    config = task_class(name).config_class(**overrides)
    config.validate()
    return config


def check_setting_names(name: str, settings: Iterable[str]) -> None:
    """ConfigError naming the settings that are not fields of task ``name``'s config, and the valid ones."""
    fields = task_class(name).config_class.field_names()
    unknown = sorted(set(settings) - set(fields))
    if unknown:
        raise ConfigError(f"unknown setting(s) {unknown} for task {name!r}; valid: {sorted(fields)}")
