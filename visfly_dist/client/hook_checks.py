"""Checks of a task's hook outputs against their contract, made on the first steps of an env.

A task's hooks are plain tensors the core combines with its own: a reward of shape ``(N, 1)``
would broadcast against the ``(N,)`` episode returns into ``(N, N)``, a float success would fail
deep in the core, an observation entry of the wrong shape would reach the trainer outside its
space. A custom task gets these wrong easily; checked once, they cost nothing per step.
"""

from __future__ import annotations

from typing import Mapping

import torch
from gymnasium import spaces

from visfly_dist.errors import TaskHookError


def check_flags(hook: str, value: object, num_envs: int) -> None:
    """``value`` (what ``hook`` returned) is a ``(num_envs,)`` bool tensor."""
    if not isinstance(value, torch.Tensor) or value.dtype != torch.bool or tuple(value.shape) != (num_envs,):
        raise TaskHookError(f"{hook}() must return a ({num_envs},) bool tensor (one flag per agent); "
                            f"it returned {_describe(value)}")


def check_reward(value: object, num_envs: int) -> None:
    """``value`` (what ``get_reward`` returned) is a ``(num_envs,)`` floating-point tensor."""
    if not isinstance(value, torch.Tensor) or not value.is_floating_point() or tuple(value.shape) != (num_envs,):
        raise TaskHookError(f"get_reward() must return a ({num_envs},) float tensor (one reward per agent); "
                            f"it returned {_describe(value)}")


def check_observation(observation: object, space: spaces.Dict, num_envs: int) -> None:
    """``observation`` (what ``get_observation`` returned) has one ``(num_envs, *shape)`` tensor per
    entry of ``space``, and no other entry."""
    if not isinstance(observation, Mapping):
        raise TaskHookError(f"get_observation() must return a dict of tensors; it returned {_describe(observation)}")
    expected, given = set(space.spaces), set(observation)
    if expected != given:
        missing, extra = sorted(expected - given), sorted(given - expected)
        raise TaskHookError("get_observation() must return exactly the entries of observation_space_dict() "
                            f"{sorted(expected)}; missing: {missing}, not in the space: {extra}")
    for key, entry in space.spaces.items():
        value, shape = observation[key], (num_envs, *(entry.shape or ()))
        if not isinstance(value, torch.Tensor) or tuple(value.shape) != shape:
            raise TaskHookError(f"get_observation()[{key!r}] must be a tensor of shape {shape} (the batch, then "
                                f"observation_space_dict()[{key!r}].shape); it is {_describe(value)}")


def _describe(value: object) -> str:
    if isinstance(value, torch.Tensor):
        return f"a {tuple(value.shape)} {str(value.dtype).removeprefix('torch.')} tensor"
    return f"a {type(value).__name__}"
