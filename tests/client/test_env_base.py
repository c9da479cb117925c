"""DroneEnvBase as an SB3 VecEnv: spaces, auto-reset semantics, infos, seeding, gradients, close."""

import os
import signal
import time

import numpy as np
import pytest
import torch
from stable_baselines3.common.vec_env import VecEnv, VecFrameStack, VecMonitor, VecNormalize

from visfly_dist.client.noise import NoiseSpec
from visfly_dist.errors import ConfigError

from tests.client.counter_task import make_counter, small_pool


@pytest.fixture(scope="module")
def env():
    noise = {"state": [NoiseSpec("gaussian", {"std": 0.01})], "depth": [NoiseSpec("gaussian", {"std": 0.05})]}
    env = make_counter(noise=noise, seed=3)
    yield env
    env.close()


def hover(env):
    return np.tile(env.quad.hover_action().numpy(), (env.num_envs, 1))


def test_spaces_and_reset_observation(env):
    assert isinstance(env, VecEnv) and env.num_envs == 4
    assert env.action_space.shape == (4,) and env.action_space.dtype == np.float32
    assert env.action_space.low.min() == -1 and env.action_space.high.max() == 1
    obs = env.reset()
    assert set(obs) == {"state", "depth", "step"}
    assert obs["state"].shape == (4, 13) and obs["state"].dtype == np.float32
    assert obs["depth"].shape == (4, 1, 16, 16) and obs["depth"].dtype == np.float32
    for i in range(4):
        assert env.observation_space.contains({k: v[i] for k, v in obs.items()})
    pos = obs["state"][:, :3]
    assert np.all(np.abs(pos - [0.0, 0.0, 2.0]) <= [1.05, 1.05, 0.55])  # spawn box (+ state noise)
    assert np.all(obs["step"] == 0)


def test_depth_sees_the_floor_at_the_right_distance(env):
    env.reset()
    level = np.tile([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], (env.num_envs, 1))
    level[:, 3:] = [np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0]  # pitched down 90 deg: camera looks at -z
    level[:, 2] = 2.0
    obs = env.aggregator.observe(level)
    centre = obs.images["depth"][:, 0, 7:9, 7:9]
    assert np.allclose(centre, 2.0, atol=0.05)  # the floor's top is z = 0


def test_time_limit_truncates_and_terminal_observation_is_the_one_before_reset(env):
    obs = env.reset()
    rewards = np.zeros(4)
    for t in range(1, 6):
        prev = obs
        obs, reward, done, infos = env.step(hover(env))
        rewards += reward
        assert reward.dtype == np.float32 and np.all(np.isfinite(reward))
        if t < 5:
            assert not done.any() and np.all(obs["step"] == t)
            assert all(info["TimeLimit.truncated"] is False and "terminal_observation" not in info for info in infos)
    assert done.all()
    for i, info in enumerate(infos):
        assert info["TimeLimit.truncated"] is True and info["is_success"] is False
        term = info["terminal_observation"]
        assert term["step"][0] == 5 and obs["step"][i, 0] == 0
        assert np.linalg.norm(term["state"][:3] - prev["state"][i, :3]) < 0.2  # continuous with the last step
        assert info["episode"]["l"] == 5 and info["episode"]["r"] == pytest.approx(rewards[i], rel=1e-5)
        assert set(term) == set(env.observation_space.spaces)


def _step_with_success(env, agent: int):
    """Reset, take one step, then a step where ``agent`` succeeds; that step's result."""
    env.reset()
    env.step(hover(env))
    env.force_success[agent] = True
    try:
        return env.step(hover(env))
    finally:
        env.force_success[:] = False


def test_success_terminates_only_that_agent(env):
    obs, _, done, infos = _step_with_success(env, 1)
    assert done.tolist() == [False, True, False, False]
    assert infos[1]["is_success"] is True and infos[1]["TimeLimit.truncated"] is False
    assert infos[1]["terminal_observation"]["step"][0] == 2 and obs["step"][1, 0] == 0
    assert obs["step"][0, 0] == 2 and "episode" not in infos[0]
    _, _, done, _ = env.step(hover(env))
    assert not done.any()


def test_terminal_observation_copies_only_the_done_rows(env):
    obs, _, _, infos = _step_with_success(env, 2)
    term = infos[2]["terminal_observation"]
    for key, row in term.items():
        assert row.base is None or row.base.shape[0] == 1, f"{key}: a view into every agent's rows"
        assert not np.shares_memory(row, obs[key])
    before = term["step"].copy()
    env.step(hover(env))  # the next step leaves the kept row alone
    assert np.array_equal(term["step"], before) and before[0] == 2


def test_step_tensor_keeps_terminated_and_truncated_apart(env):
    env.reset()
    for _ in range(4):
        env.step_tensor(torch.as_tensor(hover(env)))
    env.force_success[0] = True
    try:
        obs, reward, terminated, truncated, info = env.step_tensor(torch.as_tensor(hover(env)))
    finally:
        env.force_success[:] = False
    assert terminated.tolist() == [True, False, False, False]
    assert truncated.tolist() == [False, True, True, True]
    assert info["terminal_observation"]["step"][:, 0].tolist() == [5, 5, 5, 5]
    assert obs["step"][:, 0].tolist() == [0, 0, 0, 0] and isinstance(reward, torch.Tensor)


def test_same_seed_reproduces_the_observation_sequence(env):
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-1, 1, (4, 4)).astype(np.float32) for _ in range(7)]

    def rollout(seed):
        env.seed(seed)
        seq = [env.reset()]
        seq += [env.step(a)[0] for a in actions]
        return seq

    a, b, c = rollout(11), rollout(11), rollout(12)
    for x, y in zip(a, b):
        for k in x:
            np.testing.assert_array_equal(x[k], y[k])
    assert not np.array_equal(a[0]["state"], c[0]["state"])


def test_sb3_wrappers_step(env):
    env.reset()
    for wrapped in (VecMonitor(env), VecNormalize(env), VecFrameStack(env, n_stack=2)):
        obs = wrapped.reset()
        for _ in range(6):
            obs, reward, done, infos = wrapped.step(np.stack([env.action_space.sample() for _ in range(4)]))
            assert np.all(np.isfinite(reward))
        assert set(obs) == {"state", "depth", "step"}
    monitor = VecMonitor(env)
    monitor.reset()
    for _ in range(5):
        _, _, done, infos = monitor.step(hover(env))
    assert done.all() and infos[0]["episode"]["l"] == 5


def test_vec_env_attribute_methods(env):
    assert env.get_attr("num_envs") == [4, 4, 4, 4]
    assert env.get_attr("num_envs", indices=[1, 2]) == [4, 4]
    with pytest.raises(IndexError, match=r"env indices \[4\] out of range for num_envs=4"):
        env.get_attr("num_envs", indices=[0, 4])
    assert env.env_is_wrapped(object) == [False] * 4
    assert env.env_method("out_of_bounds", indices=0)[0].shape == (4,)
    env.set_attr("custom_flag", 1)
    assert env.custom_flag == 1
    with pytest.raises(ConfigError, match="applies to all 4 agents"):
        env.set_attr("custom_flag", 2, indices=[0])


def test_bad_action_shape_is_rejected(env):
    env.reset()
    with pytest.raises(ConfigError, match=r"actions of shape \(3, 4\) must be \(4, 4\)"):
        env.step(np.zeros((3, 4), np.float32))


def test_gradients_flow_from_reward_to_actions():
    with make_counter(num_envs=2, requires_grad=True) as env:
        env.reset()
        actions = torch.as_tensor(hover(env)).requires_grad_()
        total = 0.0
        for _ in range(3):
            _, reward, _, _, _ = env.step_tensor(actions)
            total = total + reward.sum()
        total.backward()
        assert actions.grad is not None and torch.isfinite(actions.grad).all()
        assert actions.grad[:, 0].gt(0).all()  # more thrust -> higher -> more reward
        assert env.state.pos.requires_grad
        env.detach()
        assert not env.state.pos.requires_grad
        _, reward, _, _ = env.step(hover(env))  # the SB3 path still gives numpy
        assert isinstance(reward, np.ndarray)


def test_close_is_idempotent_and_the_env_refuses_work_afterwards():
    env = make_counter(num_envs=1)
    with env:
        env.reset()
    env.close()
    with pytest.raises(ConfigError, match="closed"):
        env.reset()


def test_a_start_that_fails_reports_its_own_error_and_leaves_no_worker():
    """The env closes what it started when its workers do not come up, and the caller sees why
    (an AttributeError from the half-built env's close used to hide it)."""
    from visfly_dist.aggregator import PoolConfig
    from visfly_dist.errors import NoWorkersError

    before = _local_workers()
    with pytest.raises(NoWorkersError, match=r"0 worker\(s\) came up within startup_timeout_s=0.05"):
        make_counter(pool=PoolConfig(num_local_workers=1, backend="raycast", startup_timeout_s=0.05))
    deadline = time.monotonic() + 10.0
    while _local_workers() - before and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _local_workers() - before


def _local_workers() -> set[int]:
    """Pids of this process's worker children (``visfly_dist.cli worker``) that are still running."""
    out = set()
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            stat = open(f"/proc/{entry.name}/stat").read()
            cmdline = open(f"/proc/{entry.name}/cmdline", "rb").read()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if int(fields[1]) == os.getpid() and fields[0] != "Z" and b"worker" in cmdline:
            out.add(int(entry.name))
    return out


def test_a_group_sent_before_close_is_not_received_after_it():
    env = make_counter(num_envs=2)
    with env:
        env.reset()
        env.send(np.zeros((2, 4), np.float32), np.arange(2))
    with pytest.raises(ConfigError, match="this env is closed"):  # not a stale step, nor a worker's shutdown error
        env.recv()


def _kill_a_worker(env):
    """SIGKILL one of two local workers; the agents whose scenes it served."""
    victim = env.aggregator.workers[0]
    slots = [s for s, w in env.aggregator.assignment().items() if w == victim]
    os.kill(env.aggregator.local_worker_pids()[victim], signal.SIGKILL)
    return np.isin(env.aggregator.agent_scene, slots)


def test_agents_of_a_killed_worker_are_held_until_their_scene_is_served_again():
    with make_counter(num_envs=4, max_episode_steps=50, pool=small_pool(workers=2, respawn=False)) as env:
        env.reset()
        obs, _, _, _ = env.step(hover(env))
        affected = _kill_a_worker(env)
        held_at = obs["state"][affected, :3].copy()
        served_again, held_steps = False, 0
        for _ in range(400):  # the scenes move to the survivor in the background
            obs, reward, done, infos = env.step(hover(env))
            assert not done.any()  # nobody's episode is cut
            held = np.array([info.get("held", False) for info in infos])
            assert not (held & ~affected).any()
            assert (reward[held] == 0).all() and (obs["step"][held, 0] == 1).all()  # paused: no step, no reward
            assert np.abs(obs["state"][held, :3] - held_at[held[affected]]).max(initial=0) < 0.05  # state noise only
            held_steps += int(held.any())
            if not held.any():
                served_again = True
                break
        assert served_again and held_steps >= 1
        assert (obs["step"][affected, 0] >= 2).all()  # the episode went on from where it paused (scenes may
        # come back a step apart)
        assert not any(info.get("lost") for info in infos)


def test_lost_agents_are_cut_at_once_with_no_hold():
    with make_counter(num_envs=4, max_episode_steps=50, lost_hold_s=0.0,
                      pool=small_pool(workers=2, respawn=False)) as env:
        env.reset()
        env.step(hover(env))
        affected = _kill_a_worker(env)
        obs, _, done, infos = env.step(hover(env))
        assert done.tolist() == affected.tolist()
        for i in np.flatnonzero(affected):
            assert infos[i]["lost"] is True and infos[i]["TimeLimit.truncated"] is True
            assert infos[i]["terminal_observation"]["step"][0] == 2 and obs["step"][i, 0] == 0
