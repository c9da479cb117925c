"""Agents stepped in two groups through send/recv (the overlapped rollout) get the rewards and
observations of the plain step: a group in flight must not change what another group's step sees
(its task state, e.g. the previous distance that progress rewards are measured from)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

STEPS = 6


def _actions(env, seed: int) -> torch.Tensor:
    """``(STEPS, N, 4)``: about hover, tilted so that the agents move (and progress is not zero)."""
    rng = np.random.default_rng(seed)
    hover = env.quad.hover_action().numpy()
    return torch.as_tensor(np.clip(hover + rng.uniform(-0.3, 0.3, (STEPS, env.num_envs, 4)), -1, 1), dtype=torch.float32)


def _plain(env, actions: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    env.seed(11)
    env.reset()
    rewards, states, ended = [], [], []
    for t in range(STEPS):
        obs, reward, terminated, truncated, _ = env.step_tensor(actions[t])
        rewards.append(reward.detach().numpy())
        states.append(obs["state"].numpy())
        ended.append((terminated | truncated).numpy())
    return np.array(rewards), np.array(states), np.array(ended)


def _grouped(env, actions: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each group sent again as soon as its step is in, while the other is still in flight."""
    env.seed(11)
    env.reset()
    groups = [torch.tensor([0]), torch.tensor([1])]
    rewards, states = np.zeros((STEPS, 2)), np.zeros((STEPS, 2, 13))
    ended = np.zeros((STEPS, 2), dtype=bool)
    steps = [0, 0]
    for g, ids in enumerate(groups):
        env.send(actions[0, ids], ids)
    in_flight = 2
    while in_flight:
        (obs, reward, terminated, truncated, _), ids = env.recv()
        g = int(ids[0])
        t = steps[g]
        rewards[t, g] = float(reward[0])
        states[t, g] = obs["state"][0].numpy()
        ended[t, g] = bool((terminated | truncated)[0])
        steps[g] += 1
        if steps[g] < STEPS:
            env.send(actions[steps[g], ids], ids)
        else:
            in_flight -= 1
    return rewards, states, ended


@pytest.mark.parametrize("task", ["navigation", "racing", "hover"])
def test_two_groups_in_flight_get_the_rewards_of_the_plain_step(envs, task):
    env = envs(task)
    actions = _actions(env, seed=3)
    rewards, states, ended = _plain(env, actions)
    grouped_rewards, grouped_states, grouped_ended = _grouped(env, actions)
    live = ~np.cumsum(ended, axis=0).astype(bool) | ended   # up to and including each agent's first end
    assert live[:3].all(), "the agents should fly a few steps before any episode ends"
    assert (np.abs(rewards[live]) > 1e-6).any()
    np.testing.assert_allclose(grouped_states[live], states[live], atol=1e-5)
    np.testing.assert_allclose(grouped_rewards[live], rewards[live], atol=1e-5)
    np.testing.assert_array_equal(grouped_ended[live], ended[live])
