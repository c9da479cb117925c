"""Contracts every task keeps: pure hooks, success radius held to the end, end causes, reward signs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from visfly_dist import make_env
from visfly_dist.tasks import TASKS
from visfly_dist.tasks.outcomes import end_cause
from tests.tasks.helpers import hover, place, small

HOOKS = ("get_success", "get_failure", "get_reward", "get_observation")


def task_state(env) -> dict[str, torch.Tensor]:
    """Every tensor attribute of the env (its per-agent task state among them), cloned."""
    return {k: v.detach().clone() for k, v in vars(env).items() if isinstance(v, torch.Tensor)}


def as_tensors(value) -> list[torch.Tensor]:
    return [value[k] for k in sorted(value)] if isinstance(value, dict) else [value]


@pytest.mark.parametrize("name", list(TASKS))
def test_hooks_are_pure(envs, name):
    env = envs(name)
    env.reset()
    rng = np.random.default_rng(0)
    for _ in range(3):
        env.step(rng.uniform(-0.3, 0.3, (env.num_envs, 4)).astype(np.float32) + hover(env))
    before, config = task_state(env), env.config
    variants = ("ours", "visfly") if hasattr(config, "reward") else (None,)
    try:
        for variant in variants:
            env.config = config if variant is None else config.replace(reward=variant)
            for hook in HOOKS:
                first, second = as_tensors(getattr(env, hook)()), as_tensors(getattr(env, hook)())
                for a, b in zip(first, second, strict=True):
                    assert torch.equal(a, b), f"{name}.{hook} ({variant}) gave different results on a second call"
    finally:
        env.config = config
    after = task_state(env)
    for key, value in before.items():
        assert torch.equal(value, after[key]), f"{name}: a hook changed {key}"


@pytest.mark.parametrize("name", ["navigation", "hover"])
def test_precompute_while_rendering_changes_no_result(envs, name, monkeypatch):
    """The state-only terms computed while the workers render (``precompute``) are the ones the hooks
    would compute: the same seeded rollout with and without it gives the same steps."""
    env = envs(name)

    def rollout():
        env.seed(7)
        out = [env.reset()]
        rng = np.random.default_rng(3)
        for _ in range(6):
            obs, reward, done, _ = env.step(rng.uniform(-0.5, 0.5, (env.num_envs, 4)).astype(np.float32) + hover(env))
            out += [obs, {"reward": reward, "done": done}]
        return out

    with_it = rollout()
    monkeypatch.setattr(type(env), "precompute", lambda self: None)
    without = rollout()
    for a, b in zip(with_it, without, strict=True):
        assert sorted(a) == sorted(b)
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=f"{name}: {key} differs with precompute")


def test_racing_advances_only_in_update_task_state(envs):
    env = envs("racing")
    env.reset()
    place(env, [env.config.gates[0], env.config.gates[2]])
    assert env.get_success().tolist() == [False, False] and env.passed.tolist() == [0, 0]
    assert env.passed_now().tolist() == [1, 0]
    env.update_task_state()
    assert env.passed.tolist() == [1, 0]
    env.update_task_state()  # now gate 1 is next, and agent 0 is not at it
    assert env.passed.tolist() == [1, 0]


def end_step(env, positions, held):
    """Put agents at ``positions`` on the last step of their episode, having held for ``held`` steps."""
    env.reset()
    place(env, positions)
    env.held = torch.full((env.num_envs,), held, dtype=torch.long)
    env.episode_step = torch.full((env.num_envs,), env.config.max_episode_steps - 1, dtype=torch.long)
    return env.step(hover(env))


def test_hover_success_needs_the_radius_held_to_the_end(envs):
    env = envs("hover")
    limit, hold = env.config.max_episode_steps, env.hold_steps
    assert hold == 50 and env.config.success_radius == 0.3
    # Inside the radius vs 0.4 m away, after holding the radius for hold - 1 steps.
    _, _, done, infos = end_step(env, [[1.0, 0.0, 1.5], [1.4, 0.0, 1.5]], hold - 1)
    assert done.all()
    assert [end_cause(i, i["episode"]["l"], limit) for i in infos] == ["success", "time_limit"]
    # Inside the radius now, but not for long enough.
    _, _, done, infos = end_step(env, [[1.0, 0.0, 1.5], [1.1, 0.0, 1.5]], hold - 2)
    assert [end_cause(i, i["episode"]["l"], limit) for i in infos] == ["time_limit", "time_limit"]


def test_hover_end_causes_collision_and_out_of_bounds(envs):
    env = envs("hover")
    env.reset()
    place(env, [[1.0, 0.0, 0.05], [1.0, 0.0, 4.0]])  # in the floor; 2.5 m above the target
    _, reward, done, infos = env.step(hover(env))
    assert done.all()
    assert [end_cause(i, i["episode"]["l"], env.config.max_episode_steps) for i in infos] == ["collision", "out_of_bounds"]
    assert np.all(reward < -9)


def test_tracking_target_moves_on_the_circle_and_rewards_closeness(envs):
    env = envs("tracking")
    cfg = env.config
    obs = env.reset()
    start = np.add(cfg.path_center, (cfg.path_radius, 0.0, 0.0))
    assert np.abs(obs["state"][:, :3]).max() <= 0.31  # spawned near the target's start
    np.testing.assert_allclose(env.target().numpy(), [start, start], atol=1e-6)
    for _ in range(5):
        obs, reward, _, _ = env.step(hover(env))
    angle = cfg.path_speed * 5 * cfg.ctrl_dt
    expected = np.add(cfg.path_center, (cfg.path_radius * np.cos(angle), cfg.path_radius * np.sin(angle), 0.0))
    np.testing.assert_allclose(env.target()[0].numpy(), expected, atol=1e-5)
    assert obs["path"].shape == (2, cfg.future_points, 3)
    # Level drone: the first path point is the target relative to the drone, body = world frame.
    level = env.state.quat.detach()[:, 0] > 0.999
    rel = (env.target() - env.state.pos.detach()).numpy()
    np.testing.assert_allclose(obs["path"][level.numpy(), 0], rel[level.numpy()], atol=1e-2)
    # On the target vs 1.5 m off: positive reward vs less; 3.5 m off: out of bounds (target lost).
    target = env.target().numpy()
    place(env, [target[0], target[1] + (0.0, 1.5, 0.0)])
    assert env.get_reward()[0] > 0.8 and env.get_reward()[1] < env.get_reward()[0] - 0.5
    place(env, [target[0], target[1] + (0.0, 0.0, 3.5)])
    assert env.out_of_bounds().tolist() == [False, True]


def test_tracking_reward_pulls_hardest_across_the_success_radius(envs):
    env = envs("tracking")
    env.reset()
    target = env.target().numpy()
    rewards = []
    for d in (0.0, 0.2, 0.4, 0.6, 1.0, 1.4):  # both agents d m beside the target, at rest
        place(env, target + (0.0, d, 0.0))
        rewards.append(env.get_reward()[0].item())
    steps = -np.diff(rewards)  # reward lost per 0.2 m (the last two: per 0.4 m) farther out
    assert np.all(steps > 0)  # strictly falls with distance
    far = steps[4] / 2  # per 0.2 m from 1.0 to 1.4 m: about the linear term alone (0.1)
    assert far < 0.12 and steps[1] > 3 * far and steps[2] > 3 * far  # steepest across the 0.5 m radius
    # Matching the target's velocity pays over standing still at the same place.
    place(env, target)
    still = env.get_reward()
    env.state = dataclasses.replace(env.state, vel=env.target_velocity())
    assert np.all((env.get_reward() - still).numpy() > 0.1)


def test_tracking_success_needs_the_target_held_to_the_end(envs):
    env = envs("tracking")
    env.reset()
    env.episode_step = torch.full((2,), env.config.max_episode_steps - 1, dtype=torch.long)
    target = env.target_at(env.center, torch.full((2,), float(env.config.max_episode_steps) * env.config.ctrl_dt))
    place(env, [target[0].numpy(), target[1].numpy() + (0.8, 0.0, 0.0)])
    env.episode_step = torch.full((2,), env.config.max_episode_steps - 1, dtype=torch.long)
    env.held = torch.full((2,), env.hold_steps - 1, dtype=torch.long)
    _, _, done, infos = env.step(hover(env))
    assert done.all() and [i["is_success"] for i in infos] == [True, False]
    # success or not, the time limit cut the episode: a trainer bootstraps both alike
    assert infos[0]["TimeLimit.truncated"] and infos[1]["TimeLimit.truncated"]


@pytest.mark.parametrize("task", ["hover", "tracking"])
def test_a_success_judged_at_the_time_limit_is_a_truncation_not_a_termination(envs, task):
    """Hover and tracking could go on: their successful end is cut by the time limit like a failed
    one (truncated, not terminated), so no trainer values succeeding below failing at the end."""
    env = envs(task)
    env.reset()
    env.episode_step = torch.full((2,), env.config.max_episode_steps - 1, dtype=torch.long)
    env.held = torch.full((2,), env.hold_steps, dtype=torch.long)
    time = torch.full((2,), float(env.config.max_episode_steps) * env.config.ctrl_dt)
    goal = env.target_at(env.center, time)[0].numpy() if task == "tracking" else env.target[0].numpy()
    place(env, [goal, goal + np.array([0.0, 0.0, 0.05])])
    if task == "tracking":
        env.episode_step = torch.full((2,), env.config.max_episode_steps - 1, dtype=torch.long)
    result = env.step_tensor(hover(env))
    assert result.info["success"].tolist() == [True, True]
    assert result.truncated.tolist() == [True, True] and not result.terminated.any()


def test_visfly_reward_variant_has_no_failure_penalty(envs):
    env = envs("navigation")
    env.reset()
    place(env, [[1.0, 0.0, 0.05], [1.0, 0.0, 1.5]])  # agent 0 in the floor
    env.step(hover(env))  # agent 0 collides (and is respawned); replay its last frame's reward terms
    place(env, [[1.0, 0.0, 0.05], [1.0, 0.0, 1.5]])
    env.frame = env._frame(env.aggregator.observe(env.state.pose().detach().numpy()))
    env.failure = env.get_failure()
    env.success = env.get_success() & ~env.failure
    assert env.failure.tolist() == [True, False]
    ours = env.get_reward()
    env.config = env.config.replace(reward="visfly")
    try:
        visfly = env.get_reward()
    finally:
        env.config = env.config.replace(reward="ours")
    assert ours[0] < -4 and visfly[0] > -1  # ours: -5 on failure; VisFly: none
    assert abs(visfly[1]) < 0.2  # at rest, far from obstacles: only small shaping terms


def test_tracking_reward_is_differentiable_through_the_dynamics():
    with make_env("tracking", num_envs=1, requires_grad=True, **small(())) as env:
        env.reset()
        actions = torch.zeros(1, 4, requires_grad=True)
        for _ in range(3):
            reward = env.step_tensor(actions).reward
        reward.sum().backward()
    assert actions.grad is not None and actions.grad.abs().sum() > 0


def test_landing_rewards_a_soft_touchdown_on_the_pad_and_fails_a_hard_or_off_pad_one(envs):
    env = envs("landing")
    env.reset()
    pad = env.pad[0].numpy()

    def touch_down(positions, vz):
        place(env, np.add(pad, positions))
        env.state = dataclasses.replace(env.state, vel=torch.tensor([[0.0, 0.0, vz]] * 2))
        env.update_task_state()  # the approach term measures from here, not from the last spawn
        _, reward, done, infos = env.step(hover(env))
        causes = [end_cause(i, i["episode"]["l"], env.config.max_episode_steps) if d else None for i, d in zip(infos, done)]
        return reward, causes

    # Both in contact range of the pad (its top at 0.01 m, drone radius 0.1 m): slow wins, fast crashes.
    reward, causes = touch_down([[0.0, 0.0, 0.12], [0.1, 0.0, 0.12]], -0.1)
    assert causes == ["success", "success"] and np.all(reward > 9)  # resting on the pad is a landing
    reward, causes = touch_down([[0.0, 0.0, 0.12], [0.0, 0.0, 0.5]], -2.0)
    assert causes == ["collision", None] and reward[0] < -4
    # Slow, but beside the pad (0.6 m off its centre): a touch-down on the floor is a failure.
    reward, causes = touch_down([[0.6, 0.0, 0.08], [0.0, 0.0, 0.5]], -0.1)
    assert causes == ["collision", None] and reward[0] < -4


@pytest.mark.parametrize("brake_weight", [0.0, 0.1])
def test_landing_braking_term_pays_for_slowing_down_on_the_way_in(brake_weight):
    """Two drones 1 m above the pad descend at 0.5 and 3 m/s: without the braking term the fast
    one earns more (its approach speed), with it the slow one does (3 m/s is over the safe speed
    there, 0.2 + 0.5 * 0.9 m/s; 0.5 m/s is not)."""
    from tests.tasks.helpers import SETTINGS

    settings = dict(SETTINGS["landing"])
    settings.pop("num_envs")
    env = make_env("landing", num_envs=2, seed=1, brake_weight=brake_weight, **settings)
    try:
        env.reset()
        pad = env.pad[0].numpy()
        place(env, np.add(pad, [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]))
        env.state = dataclasses.replace(env.state, vel=torch.tensor([[0.0, 0.0, -0.5], [0.0, 0.0, -3.0]]))
        env.update_task_state()
        _, reward, done, _ = env.step(hover(env))
        assert not done.any()
        slow, fast = reward
        assert (slow > fast) if brake_weight else (fast > slow)
    finally:
        env.close()
