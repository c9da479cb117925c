"""A task's hook outputs are checked against their contract on the first step: a wrong shape,
dtype or key set is a TaskHookError naming the hook, never a silent broadcast."""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import pytest
import torch
from gymnasium import spaces

from visfly_dist.client.hook_checks import check_flags, check_observation, check_reward
from visfly_dist.errors import ConfigError, TaskHookError
from tests.client.counter_task import make_counter

N = 4
SPACE = spaces.Dict({"state": spaces.Box(-np.inf, np.inf, (13,), np.float32),
                     "depth": spaces.Box(0.0, 20.0, (1, 8, 8), np.float32)})


def good_observation() -> dict[str, torch.Tensor]:
    return {"state": torch.zeros(N, 13), "depth": torch.zeros(N, 1, 8, 8)}


def test_outputs_of_the_contract_pass() -> None:
    check_flags("get_success", torch.zeros(N, dtype=torch.bool), N)
    check_reward(torch.zeros(N, dtype=torch.float64), N)
    check_observation(good_observation(), SPACE, N)


@pytest.mark.parametrize("value, said", [
    (torch.zeros(N, 1), r"get_reward\(\) must return a \(4,\) float tensor.*a \(4, 1\) float32 tensor"),
    (torch.tensor(1.0), r"a \(\) float32 tensor"),
    (torch.zeros(N, dtype=torch.long), r"a \(4,\) int64 tensor"),
    (np.zeros(N), r"a ndarray"),
])
def test_a_reward_of_another_shape_or_type_is_refused(value: Any, said: str) -> None:
    with pytest.raises(TaskHookError, match=said):
        check_reward(value, N)


@pytest.mark.parametrize("value", [torch.zeros(N), torch.zeros(N, 1, dtype=torch.bool), torch.zeros(N + 1, dtype=torch.bool)])
def test_flags_must_be_one_bool_per_agent(value: torch.Tensor) -> None:
    with pytest.raises(TaskHookError, match=r"get_failure\(\) must return a \(4,\) bool tensor"):
        check_flags("get_failure", value, N)


def test_observation_entries_must_match_the_space() -> None:
    with pytest.raises(TaskHookError, match=r"missing: \['depth'\], not in the space: \[\]"):
        check_observation({"state": torch.zeros(N, 13)}, SPACE, N)
    with pytest.raises(TaskHookError, match=r"missing: \[\], not in the space: \['extra'\]"):
        check_observation({**good_observation(), "extra": torch.zeros(N, 1)}, SPACE, N)
    with pytest.raises(TaskHookError, match=r"\['depth'\] must be a tensor of shape \(4, 1, 8, 8\).*\(4, 8, 8\)"):
        check_observation({**good_observation(), "depth": torch.zeros(N, 8, 8)}, SPACE, N)
    with pytest.raises(TaskHookError, match="a dict of tensors; it returned a list"):
        check_observation([torch.zeros(N, 13)], SPACE, N)
    assert issubclass(TaskHookError, ConfigError)


def test_a_real_task_with_a_wrong_hook_fails_its_first_step_naming_the_hook() -> None:
    """Each mistake of a custom task, on a real env: the step raises, and once the hook is right
    the env steps on (reward, returns and dones keep their shapes)."""
    mistakes: list[tuple[str, Callable[[Any], Any], str]] = [
        ("get_reward", lambda env: env.state.pos[:, 2:3], r"get_reward\(\).*\(2, 1\)"),
        ("get_success", lambda env: env.force_success.float(), r"get_success\(\).*float32"),
        ("get_failure", lambda env: torch.zeros(2, 1, dtype=torch.bool), r"get_failure\(\).*\(2, 1\) bool"),
        ("get_observation", lambda env: {"state": env.state_vector(), **env.frame.images},
         r"missing: \['step'\]"),
    ]
    with make_counter(num_envs=2) as env:
        for hook, wrong, said in mistakes:
            right = getattr(env, hook)
            setattr(env, hook, lambda wrong=wrong: wrong(env))
            with pytest.raises(TaskHookError, match=said):
                env.step_tensor(torch.zeros(2, 4))
            setattr(env, hook, right)
        result = env.step_tensor(torch.zeros(2, 4))
        assert result.reward.shape == (2,) and env.episode_return.shape == (2,)
        assert result.terminated.shape == result.truncated.shape == (2,)
