"""The tensor PPO's parts against SB3's (normalisation, GAE), and a real run: episodes, checkpoints, eval."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.logger import configure
from stable_baselines3.common.running_mean_std import RunningMeanStd

from visfly_dist.training.checkpoints import load_normalization, norm_path
from visfly_dist.training.config import TrainConfig
from visfly_dist.training.evaluation import build_eval_env, evaluate, load_policy
from visfly_dist.training.ppo import train
from visfly_dist.training.tensor_ppo import CLIP_OBS, EPSILON, Normalizer, Rollout, RunningMoments, TensorPPO

from tests.client.counter_task import make_counter

CPU = torch.device("cpu")


def test_running_moments_match_sb3s_running_mean_std() -> None:
    rng = np.random.default_rng(0)
    ours, theirs = RunningMoments((3,), CPU), RunningMeanStd(shape=(3,))
    for n in (1, 7, 64, 2):
        batch = rng.normal(2.0, 3.0, size=(n, 3))
        ours.update(torch.as_tensor(batch))
        theirs.update(batch)
    np.testing.assert_allclose(ours.mean.numpy(), theirs.mean, rtol=1e-12)
    np.testing.assert_allclose(ours.var.numpy(), theirs.var, rtol=1e-12)
    assert ours.count == pytest.approx(theirs.count)


def test_normalizer_gives_vecnormalizes_observations_and_rewards() -> None:
    """The same formulas as SB3's VecNormalize (obs: update then scale and clip; rewards: scaled by
    the spread of discounted returns that restart at episode ends), images untouched. Each vector
    entry has statistics of its own, whatever its shape, though they are updated together."""
    space = spaces.Dict({"state": spaces.Box(-np.inf, np.inf, (2,), np.float32),
                         "depth": spaces.Box(0, 20, (1, 4, 4), np.float32),
                         "target": spaces.Box(-np.inf, np.inf, (2, 3), np.float32)})
    norm = Normalizer(space, num_envs=3, gamma=0.9, device=CPU)
    obs_rms, ret_rms, returns = RunningMeanStd(shape=(2,)), RunningMeanStd(shape=()), np.zeros(3)
    target_rms = RunningMeanStd(shape=(2, 3))
    rng = np.random.default_rng(1)
    for step in range(20):
        state = rng.normal(5.0, 2.0, size=(3, 2)).astype(np.float32)
        depth = rng.uniform(0, 20, size=(3, 1, 4, 4)).astype(np.float32)
        reward = rng.normal(size=3).astype(np.float32)
        done = rng.random(3) < 0.2
        target = rng.normal(-3.0, 0.5, size=(3, 2, 3)).astype(np.float32)
        out = norm.observe({"state": torch.as_tensor(state), "depth": torch.as_tensor(depth), "target": torch.as_tensor(target)})
        obs_rms.update(state)
        target_rms.update(target)
        expected = np.clip((state - obs_rms.mean) / np.sqrt(obs_rms.var + EPSILON), -CLIP_OBS, CLIP_OBS)
        np.testing.assert_allclose(out["state"].numpy(), expected, rtol=1e-5, atol=1e-6)
        expected = np.clip((target - target_rms.mean) / np.sqrt(target_rms.var + EPSILON), -CLIP_OBS, CLIP_OBS)
        np.testing.assert_allclose(out["target"].numpy(), expected, rtol=1e-5, atol=1e-6)
        assert out["target"].shape == (3, 2, 3) and out["target"].dtype == torch.float32
        assert np.array_equal(out["depth"].numpy(), depth)
        scaled = norm.reward(torch.as_tensor(reward), torch.as_tensor(done))
        returns = returns * 0.9 + reward
        ret_rms.update(returns)
        np.testing.assert_allclose(scaled.numpy(), np.clip(reward / np.sqrt(ret_rms.var + EPSILON), -10, 10), rtol=1e-5)
        returns[done] = 0
    np.testing.assert_allclose(norm.obs_moments["target"].var.numpy(), target_rms.var, rtol=1e-6)


def test_saved_statistics_load_as_a_frozen_vecnormalize(tmp_path: Path) -> None:
    from stable_baselines3.common.vec_env import DummyVecEnv
    import gymnasium as gym

    space = spaces.Dict({"state": spaces.Box(-np.inf, np.inf, (2,), np.float32)})
    norm = Normalizer(space, num_envs=2, gamma=0.99, device=CPU)
    norm.observe({"state": torch.tensor([[1.0, 2.0], [3.0, 6.0]])})
    norm.reward(torch.tensor([1.0, -1.0]), torch.tensor([False, False]))
    norm.save(tmp_path / "x.norm.npz")

    class Probe(gym.Env):
        observation_space, action_space = space, spaces.Box(-1, 1, (4,), np.float32)

        def reset(self, seed=None, options=None):
            return {"state": np.zeros(2, np.float32)}, {}

        def step(self, action):
            return {"state": np.zeros(2, np.float32)}, 0.0, False, False, {}

    venv = load_normalization(DummyVecEnv([Probe]), tmp_path / "x.norm.npz")
    np.testing.assert_allclose(venv.obs_rms["state"].mean, norm.obs_moments["state"].mean.numpy())
    np.testing.assert_allclose(venv.obs_rms["state"].var, norm.obs_moments["state"].var.numpy())
    np.testing.assert_allclose(venv.ret_rms.var, norm.ret_moments.var.numpy())
    assert venv.training is False and venv.norm_reward


def test_kept_images_gather_the_rows_a_copied_rollout_gives() -> None:
    """A rollout that keeps each step's images as handed out (no copy) gathers a minibatch's rows
    exactly as a rollout that copied them in; vector entries are copied either way."""
    space = spaces.Dict({"state": spaces.Box(-np.inf, np.inf, (3,), np.float32),
                         "depth": spaces.Box(0, 20, (1, 4, 5), np.float32)})
    steps, envs = 6, 5
    kept, copied = Rollout(space, steps, envs, CPU, kept_images=True), Rollout(space, steps, envs, CPU)
    assert set(kept.images) == {"depth"} and not copied.images
    gen = torch.Generator().manual_seed(0)
    for rollout in range(2):  # the second rollout replaces the first one's images
        handed_out = []
        for t in range(steps):
            obs = {"state": torch.randn(envs, 3, generator=gen), "depth": torch.rand(envs, 1, 4, 5, generator=gen)}
            kept.store_observation(t, slice(None), obs)
            copied.store_observation(t, slice(None), obs)
            handed_out.append(obs["depth"])
        assert all(a is b for a, b in zip(kept.images["depth"], handed_out))  # kept, not copied
        for idx in (torch.arange(steps * envs), torch.tensor([0, 4, 5, 17, 29]), torch.tensor([7]),
                    torch.randperm(steps * envs, generator=gen)[:11].sort().values):
            ours, theirs = kept.gather_observations(idx), copied.gather_observations(idx)
            assert all(torch.equal(ours[k], theirs[k]) for k in ("state", "depth"))


def test_gae_matches_sb3s_rollout_buffer() -> None:
    rng = np.random.default_rng(2)
    steps, envs, gamma, lam = 9, 4, 0.97, 0.9
    rewards = rng.normal(size=(steps, envs)).astype(np.float32)
    values = rng.normal(size=(steps, envs)).astype(np.float32)
    dones = rng.random((steps, envs)) < 0.25
    last_values = rng.normal(size=envs).astype(np.float32)

    space = spaces.Dict({"state": spaces.Box(-1, 1, (1,), np.float32)})
    ours = Rollout(space, steps, envs, CPU)
    ours.rewards[:], ours.values[:], ours.dones[:] = torch.as_tensor(rewards), torch.as_tensor(values), torch.as_tensor(dones)
    ours.compute_gae(torch.as_tensor(last_values), gamma, lam)

    sb3 = RolloutBuffer(steps, spaces.Box(-1, 1, (1,), np.float32), spaces.Box(-1, 1, (4,), np.float32),
                        gamma=gamma, gae_lambda=lam, n_envs=envs)
    sb3.rewards[:], sb3.values[:] = rewards, values
    sb3.episode_starts[0] = 0.0
    sb3.episode_starts[1:] = dones[:-1]  # an episode starts after a done
    sb3.compute_returns_and_advantage(torch.as_tensor(last_values), dones[-1])
    np.testing.assert_allclose(ours.advantages.numpy(), sb3.advantages, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(ours.returns.numpy(), sb3.returns, rtol=1e-5, atol=1e-6)


def test_gae_passes_over_held_steps_as_if_they_never_happened() -> None:
    """An agent held while its worker was replaced has steps that are no transitions: its advantages
    and returns on the other steps equal those of the same rollout with the held steps cut out."""
    rng = np.random.default_rng(3)
    steps, envs, gamma, lam = 12, 3, 0.95, 0.9
    rewards = rng.normal(size=(steps, envs)).astype(np.float32)
    values = rng.normal(size=(steps, envs)).astype(np.float32)
    dones = rng.random((steps, envs)) < 0.2
    held = np.zeros((steps, envs), dtype=bool)
    held[3:6, 0] = held[10:, 1] = held[0, 2] = True
    dones[held] = False
    rewards[held] = 0.0
    last_values = rng.normal(size=envs).astype(np.float32)
    space = spaces.Dict({"state": spaces.Box(-1, 1, (1,), np.float32)})
    ours = Rollout(space, steps, envs, CPU)
    ours.rewards[:], ours.values[:] = torch.as_tensor(rewards), torch.as_tensor(values)
    ours.dones[:], ours.held[:] = torch.as_tensor(dones), torch.as_tensor(held)
    ours.compute_gae(torch.as_tensor(last_values), gamma, lam)
    for env in range(envs):
        kept = ~held[:, env]
        alone = Rollout(space, int(kept.sum()), 1, CPU)
        alone.rewards[:, 0] = torch.as_tensor(rewards[kept, env])
        alone.values[:, 0] = torch.as_tensor(values[kept, env])
        alone.dones[:, 0] = torch.as_tensor(dones[kept, env])
        alone.compute_gae(torch.as_tensor(last_values[env:env + 1]), gamma, lam)
        np.testing.assert_allclose(ours.advantages[kept, env].numpy(), alone.advantages[:, 0].numpy(), rtol=1e-5)
        np.testing.assert_allclose(ours.returns[kept, env].numpy(), alone.returns[:, 0].numpy(), rtol=1e-5)


def test_held_rows_leave_the_reward_statistics_alone() -> None:
    """A held row's step did not happen: its discounted return stays, and it is not a sample of the
    return statistics (VecNormalize's formulas over the other rows only)."""
    space = spaces.Dict({"state": spaces.Box(-1, 1, (1,), np.float32)})
    norm, ret_rms, returns = Normalizer(space, 2, 0.9, CPU), RunningMeanStd(shape=()), np.zeros(2)
    rng = np.random.default_rng(4)
    for step in range(10):
        reward = rng.normal(size=2).astype(np.float32)
        held = np.array([False, step % 3 == 0])
        scaled = norm.reward(torch.as_tensor(reward), torch.tensor([False, False]), held=torch.as_tensor(held))
        returns = np.where(held, returns, returns * 0.9 + reward)
        ret_rms.update(returns[~held])
        np.testing.assert_allclose(norm.returns.numpy(), returns, rtol=1e-6)
        expected = np.clip(reward / np.sqrt(ret_rms.var + EPSILON), -10, 10)
        np.testing.assert_allclose(scaled.numpy()[~held], expected[~held], rtol=1e-5)
    assert norm.ret_moments.count == pytest.approx(ret_rms.count)


def test_a_tensor_ppo_run_counts_episodes_and_writes_checkpoints_eval_loads(tmp_path: Path) -> None:
    """Gap crossing (teams of 3, two overlapped groups of whole teams): episodes reach the curve,
    checkpoints and the final model are SB3 files with statistics, and eval runs them."""
    cfg = TrainConfig(task="gap_crossing", algo="ppo", num_envs=6, workers=1, timesteps=384, n_steps=32,
                      batch_size=64, n_epochs=1, overlap=True, checkpoint_every=192, progress=False,
                      out=str(tmp_path / "run"), overrides={"max_episode_steps": 12})
    result = train(cfg)
    assert result.config.algo == "ppo" and result.config.overlap and result.timesteps >= 384
    assert result.summary["rollout_s"] > 0 and result.summary["update_s"] > 0
    assert not np.isnan(result.summary["success_rate"])  # 12-step episodes ended and were counted
    checkpoints = sorted((tmp_path / "run" / "checkpoints").glob("step_*.zip"))
    assert [p.name for p in checkpoints] == ["step_192.zip", "step_384.zip"]
    assert all(norm_path(p).is_file() for p in [*checkpoints, result.final_model])
    curve = (tmp_path / "run" / "success_curve.csv").read_text().splitlines()
    assert curve[0].startswith("timesteps") and len(curve) >= 2

    env = build_eval_env("gap_crossing", 3, 5, result.config, {"max_episode_steps": 12}, {})
    try:
        model, env = load_policy(result.final_model, env)
        stats = evaluate(model, env, episodes=3)
    finally:
        env.close()
    assert stats.episodes == 3


def test_episodes_cut_by_the_time_limit_are_bootstrapped_from_their_own_terminal_view() -> None:
    """A truncated agent's reward gains ``gamma * V(its terminal observation)`` (SB3's TimeLimit
    handling), also when the step hands out only the ended agents' terminal rows and an agent that
    did not end comes before one that did (agent 0 is pushed out of phase by an early success)."""
    env = make_counter(seed=1)
    try:
        model = PPO("MultiInputPolicy", env, n_steps=12, batch_size=16, gamma=0.9, device="cpu", seed=0)
        trainer = TensorPPO(model, env, normalize=False)
        trainer.reset()
        seen, step = [], env.step_tensor

        def recorded(actions, hold=None, terminal="all"):
            env.force_success[0] = len(seen) == 1
            result = step(actions, hold, terminal)
            seen.append(result)
            return result

        env.step_tensor = recorded
        trainer.collect()
        cut_steps = 0
        for t, (obs, reward, terminated, truncated, info) in enumerate(seen):
            ended = (terminated | truncated).nonzero().squeeze(1).tolist()
            expected = reward.clone()
            for i in truncated.nonzero().squeeze(1).tolist():
                row = {k: v[ended.index(i)][None] for k, v in info["terminal_observation"].items()}
                with torch.no_grad():
                    expected[i] += 0.9 * model.policy.predict_values(row).item()
            cut_steps += bool(truncated.any() and not truncated[0])
            torch.testing.assert_close(trainer.rollout.rewards[t], expected.to(trainer.rollout.rewards.dtype))
        assert cut_steps >= 1  # agents 1-3 were cut while agent 0 flew on
    finally:
        env.close()


def test_overlapped_groups_bootstrap_cut_episodes_from_their_own_terminal_view() -> None:
    """The same with two groups in flight: each group's step hands out only its ended agents'
    terminal rows, and agent 0's early success puts it out of phase with agent 1 of its group."""
    env = make_counter(seed=1)
    try:
        model = PPO("MultiInputPolicy", env, n_steps=12, batch_size=16, gamma=0.9, device="cpu", seed=0)
        trainer = TensorPPO(model, env, normalize=False, overlap=True)
        trainer.reset()
        seen, recv = [], env.recv

        def recorded(timeout_s=None, terminal="all"):
            env.force_success[0] = len(seen) == 2
            result, ids = recv(timeout_s, terminal)
            seen.append((result, ids))
            return result, ids

        env.recv = recorded
        trainer.collect()
        steps, cut_steps = [0, 0], 0
        for (obs, reward, terminated, truncated, info), ids in seen:
            g, ended = int(ids[0]) // 2, (terminated | truncated).nonzero().squeeze(1).tolist()
            expected = reward.clone()
            for i in truncated.nonzero().squeeze(1).tolist():
                assert len(next(iter(info["terminal_observation"].values()))) == len(ended)
                row = {k: v[ended.index(i)][None] for k, v in info["terminal_observation"].items()}
                with torch.no_grad():
                    expected[i] += 0.9 * model.policy.predict_values(row).item()
            cut_steps += bool(truncated.any() and not truncated[0]) and g == 0
            torch.testing.assert_close(trainer.rollout.rewards[steps[g], ids], expected.to(trainer.rollout.rewards.dtype))
            steps[g] += 1
        assert steps == [12, 12] and cut_steps >= 1  # agent 1 was cut while agent 0 of its group flew on
    finally:
        env.close()


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a GPU torch can use"))])
def test_statistics_stay_beside_the_env_and_the_rollout_on_the_learners_device(device: str) -> None:
    """Rewards and vector observations are normalised on the env's device (the host) before the
    step's one copy; the rollout, cut episodes' bootstraps included, lives on the learner's device
    and holds the scaled rewards the host computed (plus the bootstrap where an episode was cut)."""
    env = make_counter(seed=1)
    try:
        model = PPO("MultiInputPolicy", env, n_steps=12, batch_size=16, gamma=0.9, device=device, seed=0)
        model.set_logger(configure(None, []))
        trainer = TensorPPO(model, env, normalize=True)
        steps, step = [], env.step_tensor

        def recorded(actions, hold=None, terminal="all"):
            result = step(actions, hold, terminal)
            _, reward, terminated, truncated, _ = result
            steps.append((reward.clone(), terminated | truncated, truncated.clone()))
            return result

        env.step_tensor = recorded
        trainer.reset()
        trainer.collect()
        trainer.update()
        assert trainer.norm.returns.device.type == "cpu" and trainer.norm.ret_moments.mean.device.type == "cpu"
        assert trainer.rollout.rewards.device.type == device and trainer.rollout.observations["state"].device.type == device
        reference = Normalizer(env.observation_space, env.num_envs, 0.9, CPU, native=False)
        cut = 0
        for t, (reward, ended, truncated) in enumerate(steps):
            expected = reference.reward(reward.to(torch.float32), ended)
            kept = ~truncated  # cut rows add gamma * V(terminal) on the device
            cut += int(truncated.sum())
            torch.testing.assert_close(trainer.rollout.rewards[t].cpu()[kept], expected[kept])
        assert cut >= 1 and trainer.norm.ret_moments.count >= 12 * env.num_envs
    finally:
        env.close()


def test_each_overlapped_group_acts_on_the_observation_its_last_step_handed_out() -> None:
    """Two groups in flight: the rollout stores, for each group at step t + 1, the rows its step t
    returned (the reset's at t = 0); the rollout's last values read each group's latest rows."""
    env = make_counter(seed=2)
    try:
        model = PPO("MultiInputPolicy", env, n_steps=6, batch_size=8, device="cpu", seed=0)
        trainer = TensorPPO(model, env, normalize=False, overlap=True)
        assert [g.tolist() for g in trainer.groups] == [[0, 1], [2, 3]]
        returned: dict[int, list[dict[str, torch.Tensor]]] = {0: [], 1: []}
        recv = env.recv

        def recorded(timeout_s=None, terminal="all"):
            result, ids = recv(timeout_s, terminal)
            returned[int(ids[0]) // 2].append({k: v.clone() for k, v in result.observation.items()})
            return result, ids

        env.recv = recorded
        first = {k: torch.as_tensor(v) for k, v in env.reset().items()}
        env.reset = lambda: first  # the trainer's reset takes these rows
        trainer.reset()
        trainer.collect()
        stored = trainer.rollout.observations
        for g, rows in enumerate(trainer.groups):
            assert len(returned[g]) == 6
            for key in ("state", "step", "depth"):
                torch.testing.assert_close(stored[key][0, rows], first[key][rows])
                for t in range(5):
                    torch.testing.assert_close(stored[key][t + 1, rows], returned[g][t][key])
        latest = trainer._observation()  # every agent's view, for the rollout's last values
        for g, rows in enumerate(trainer.groups):
            for key in ("state", "step", "depth"):
                torch.testing.assert_close(latest[key][rows], returned[g][-1][key])
    finally:
        env.close()


def test_each_ended_episode_is_recorded_with_its_own_flags_return_and_length() -> None:
    """Only the ended rows reach the episode log, in index order, each with its own end flags."""
    from types import SimpleNamespace

    n = 6
    flags = {k: torch.zeros(n, dtype=torch.bool) for k in ("success", "collision", "out_of_bounds", "lost", "swapped")}
    flags["success"][1] = flags["collision"][4] = flags["out_of_bounds"][4] = True
    flags["lost"][0] = flags["swapped"][2] = True  # rows that did not end this step: not recorded
    done = torch.tensor([False, True, False, False, True, True])
    truncated = torch.tensor([False, False, False, False, False, True])
    info = {**flags, "episode_return": torch.arange(n, dtype=torch.float32) * 0.5,
            "episode_length": torch.arange(n) * 10}
    recorded: list[dict] = []
    TensorPPO._record_episodes(SimpleNamespace(_on_episode=recorded.append), done, truncated, info)
    assert [(e["episode"]["r"], e["episode"]["l"]) for e in recorded] == [(0.5, 10), (2.0, 40), (2.5, 50)]
    assert [(e["is_success"], e["collision"], e["out_of_bounds"], e["lost"], e["swapped"], e["TimeLimit.truncated"])
            for e in recorded] == [(True, False, False, False, False, False), (False, True, True, False, False, False),
                                   (False, False, False, False, False, True)]
    assert all(type(v) is bool for e in recorded for k, v in e.items() if k != "episode")
