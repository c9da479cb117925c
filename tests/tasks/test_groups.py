"""Agents stepped in two groups through send/recv (the overlapped rollout) get the rewards and
observations of the plain step: a group in flight must not change what another group's step sees
(its task state, e.g. the previous distance that progress rewards are measured from)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.tasks.helpers import SETTINGS
from visfly_dist import make_env

STEPS = 6


def _actions(env, seed: int) -> torch.Tensor:
    """``(STEPS, N, 4)``: about hover, tilted so that the agents move (and progress is not zero)."""
    rng = np.random.default_rng(seed)
    hover = env.quad.hover_action().numpy()
    return torch.as_tensor(np.clip(hover + rng.uniform(-0.3, 0.3, (STEPS, env.num_envs, 4)), -1, 1), dtype=torch.float32)


def _start(env, held: torch.Tensor | None) -> None:
    """Seed and reset; with ``held``, one step in which those agents are held (their episodes are
    then a step behind the others', so that a group's episodes end at different steps)."""
    env.seed(11)
    env.reset()
    if held is not None:
        env.step_tensor(torch.as_tensor(env.quad.hover_action()).expand(env.num_envs, 4), hold=held)


def _plain(env, actions: torch.Tensor, held: torch.Tensor | None = None
           ) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray, dict[str, np.ndarray]]:
    """Rewards, observations, ends and terminal observations, ``(STEPS, N, ...)`` each."""
    _start(env, held)
    rewards, ended = [], []
    observations: dict[str, list[np.ndarray]] = {}
    terminal: dict[str, list[np.ndarray]] = {}
    for t in range(STEPS):
        obs, reward, terminated, truncated, info = env.step_tensor(actions[t])
        rewards.append(reward.detach().numpy())
        ended.append((terminated | truncated).numpy())
        for k, v in obs.items():
            observations.setdefault(k, []).append(v.detach().numpy().copy())
        for k, v in info["terminal_observation"].items():
            terminal.setdefault(k, []).append(v.detach().numpy().copy())
    stack = lambda d: {k: np.array(v) for k, v in d.items()}  # noqa: E731
    return np.array(rewards), stack(observations), np.array(ended), stack(terminal)


def _grouped(env, actions: torch.Tensor, groups: list[torch.Tensor] | None = None, terminal_rows: str = "all",
             held: torch.Tensor | None = None) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray, dict[str, np.ndarray]]:
    """Each group sent again as soon as its step is in, while the other is still in flight. What
    ``recv`` returned is kept as it was (later steps write nothing into it). ``terminal_rows``:
    ``recv``'s ``terminal``; with ``"ended"`` only the ended agents' terminal rows are filled in."""
    _start(env, held)
    groups = groups or [torch.tensor([0]), torch.tensor([1])]
    n = env.num_envs
    rewards = np.zeros((STEPS, n))
    ended = np.zeros((STEPS, n), dtype=bool)
    observations: dict[str, np.ndarray] = {}
    terminal: dict[str, np.ndarray] = {}
    kept = []
    steps = [0] * len(groups)
    for g, ids in enumerate(groups):
        env.send(actions[0, ids], ids)
    in_flight = len(groups)
    while in_flight:
        result, ids = env.recv(terminal=terminal_rows)
        obs, reward, terminated, truncated, info = result
        g = next(i for i, group in enumerate(groups) if torch.equal(group, ids))
        t = steps[g]
        agents = ids.numpy()
        rewards[t, agents] = reward.detach().numpy()
        ended[t, agents] = (terminated | truncated).numpy()
        terminal_agents = agents if terminal_rows == "all" else agents[(terminated | truncated).numpy()]
        for out, entries, rows in ((observations, obs, agents), (terminal, info["terminal_observation"], terminal_agents)):
            for k, v in entries.items():
                assert len(v) == len(rows), f"{k}: {len(v)} rows for agents {rows.tolist()}"
                out.setdefault(k, np.zeros((STEPS, n, *v.shape[1:]), v.detach().numpy().dtype))[t, rows] = v.detach().numpy()
        kept.append((obs, info["terminal_observation"], {k: v.clone() for k, v in obs.items()},
                     {k: v.clone() for k, v in info["terminal_observation"].items()}))
        steps[g] += 1
        if steps[g] < STEPS:
            env.send(actions[steps[g], ids], ids)
        else:
            in_flight -= 1
    for obs, term, obs_then, term_then in kept:
        for now, then in ((obs, obs_then), (term, term_then)):
            for k in then:
                assert torch.equal(now[k], then[k]), f"{k} returned by recv changed afterwards"
    return rewards, observations, ended, terminal


@pytest.mark.parametrize("task", ["navigation", "racing", "hover", "tracking", "landing"])
def test_two_groups_in_flight_get_the_rewards_of_the_plain_step(envs, task):
    env = envs(task)
    actions = _actions(env, seed=3)
    rewards, observations, ended, terminal = _plain(env, actions)
    grouped_rewards, grouped_observations, grouped_ended, grouped_terminal = _grouped(env, actions)
    live = ~np.cumsum(ended, axis=0).astype(bool) | ended   # up to and including each agent's first end
    assert live[:3].all(), "the agents should fly a few steps before any episode ends"
    assert (np.abs(rewards[live]) > 1e-6).any()
    assert sorted(grouped_observations) == sorted(observations)
    for k, v in observations.items():  # images included: a group's rows merged into the frame
        np.testing.assert_allclose(grouped_observations[k][live], v[live], atol=1e-5, err_msg=k)
        np.testing.assert_allclose(grouped_terminal[k][live], terminal[k][live], atol=1e-5, err_msg=k)
    np.testing.assert_allclose(grouped_rewards[live], rewards[live], atol=1e-5)
    np.testing.assert_array_equal(grouped_ended[live], ended[live])


@pytest.mark.parametrize("terminal_rows", ["all", "ended"])
def test_groups_whose_episodes_end_get_the_first_views_and_terminal_observations_of_the_plain_step(terminal_rows):
    """Episodes cut every two steps: each group's reset merges fresh rows into the env's frame
    while the other group is in flight; every step matches the plain step, reset rows included."""
    settings = dict(SETTINGS["navigation"])
    env = make_env("navigation", num_envs=settings.pop("num_envs"), seed=1, max_episode_steps=2, **settings)
    try:
        actions = _actions(env, seed=5)
        rewards, observations, ended, terminal = _plain(env, actions)
        grouped_rewards, grouped_observations, grouped_ended, grouped_terminal = _grouped(
            env, actions, terminal_rows=terminal_rows)
    finally:
        env.close()
    assert ended[1].all() and ended[3].all()
    for k, v in observations.items():
        assert not np.array_equal(terminal[k][1], v[1]), f"{k}: the first view of a new episode is not the terminal one"
        np.testing.assert_allclose(grouped_observations[k], v, atol=1e-5, err_msg=k)
        np.testing.assert_allclose(grouped_terminal[k][ended], terminal[k][ended], atol=1e-5, err_msg=k)
        if terminal_rows == "all":
            np.testing.assert_allclose(grouped_terminal[k], terminal[k], atol=1e-5, err_msg=k)
    np.testing.assert_allclose(grouped_rewards, rewards, atol=1e-5)
    np.testing.assert_array_equal(grouped_ended, ended)


@pytest.mark.parametrize("terminal_rows", ["all", "ended"])
def test_groups_of_several_agents_whose_episodes_end_apart_match_the_plain_step(terminal_rows):
    """Two groups of two, one agent of each a step behind the other: in every group step one
    agent's episode ends and the other's goes on, so the reset agents' first views are written
    into the group's rows at their own places (and only the ended rows are terminal with "ended")."""
    settings = dict(SETTINGS["navigation"], num_envs=4)
    env = make_env("navigation", num_envs=settings.pop("num_envs"), seed=1, max_episode_steps=2, **settings)
    held = torch.tensor([False, True, True, False])
    try:
        actions = _actions(env, seed=7)
        rewards, observations, ended, terminal = _plain(env, actions, held)
        grouped_rewards, grouped_observations, grouped_ended, grouped_terminal = _grouped(
            env, actions, [torch.tensor([0, 1]), torch.tensor([2, 3])], terminal_rows, held)
    finally:
        env.close()
    assert (ended.sum(axis=1) == 2).all() and not ended.all(axis=1).any(), "half the agents end each step"
    for k, v in observations.items():
        np.testing.assert_allclose(grouped_observations[k], v, atol=1e-5, err_msg=k)
        np.testing.assert_allclose(grouped_terminal[k][ended], terminal[k][ended], atol=1e-5, err_msg=k)
    np.testing.assert_allclose(grouped_rewards, rewards, atol=1e-5)
    np.testing.assert_array_equal(grouped_ended, ended)
