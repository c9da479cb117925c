"""Recurrent policies (``visfly-dist train --recurrent``, issue #25): sb3-contrib RecurrentPPO.

A short real training run on hover writes a RecurrentPPO checkpoint; ``visfly-dist eval`` loads and
evaluates it; its LSTM state is zeroed exactly where an agent's episode starts (a crafted sequence,
and ``evaluate`` on a real env); ``visfly-dist export`` puts the actor LSTM's (h, c) in and out of the
ONNX graph, and the standalone runner (no torch) closing the loop with it matches the torch policy,
state carried over 50 real steps and reset at an episode start, to 1e-5.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from stable_baselines3.common.vec_env import VecMonitor

from tests.training.test_export import run_runner
from visfly_dist.cli import main
from visfly_dist.errors import ConfigError
from visfly_dist.tasks import make_env
from visfly_dist.training.config import TrainConfig
from visfly_dist.training.evaluation import evaluate, is_recurrent, is_recurrent_checkpoint, load_policy
from visfly_dist.training.export import LstmCore, read_metadata
from visfly_dist.training.ppo import RECURRENT_HIDDEN, env_kwargs

LOCAL = ["--workers", "1", "--backend", "raycast"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``visfly-dist train hover --recurrent --algo ppo`` for 256 steps: the run folder (the tensor
    trainer has no recurrent core: the run says so and trains in SB3's loop)."""
    run_dir = tmp_path_factory.mktemp("recurrent") / "run"
    assert main(["train", "hover", "--recurrent", "--algo", "ppo", "--timesteps", "256", "--num-envs", "2", "--n-steps", "64",
                 "--batch-size", "64", "--n-epochs", "2", "--checkpoint-every", "0", "--quiet", "--seed", "1",
                 "--out", str(run_dir), *LOCAL]) == 0
    return run_dir


def hover_env(seed: int, max_steps: int, n: int = 2) -> VecMonitor:
    cfg = TrainConfig(task="hover", num_envs=n, workers=1, backend="raycast", seed=seed,
                      overrides={"max_episode_steps": max_steps}).resolved()
    return VecMonitor(make_env("hover", num_envs=n, **env_kwargs(cfg)))


def test_training_writes_a_recurrent_checkpoint(trained: Path) -> None:
    config = json.loads((trained / "config.json").read_text())
    assert config["recurrent"] is True and config["algo"] == "sb3-ppo"  # --algo ppo fell back to SB3's loop
    assert is_recurrent_checkpoint(trained / "final.zip") and (trained / "final.norm.npz").is_file()
    rows = (trained / "success_curve.csv").read_text().splitlines()
    assert len(rows) >= 3  # a header and one row per rollout (2 rollouts of 128 steps)


def test_eval_loads_and_evaluates_it(trained: Path, tmp_path: Path) -> None:
    out = tmp_path / "eval.json"
    assert main(["eval", "hover", "--checkpoint", str(trained / "final.zip"), "--episodes", "4", "--num-envs", "2",
                 "--json", str(out), "--set", "max_episode_steps=24", *LOCAL]) == 0
    report = json.loads(out.read_text())
    for mode in ("deterministic", "sampled"):
        assert report["results"][mode]["episodes"] == 4


def test_hidden_state_resets_where_an_episode_starts(trained: Path) -> None:
    """A crafted sequence of 12 steps for 2 agents; agent 0 starts a new episode at step 5."""
    env = hover_env(seed=2, max_steps=100)
    try:
        model, env = load_policy(trained / "final.zip", env)
    finally:
        env.close()
    assert is_recurrent(model)
    rng = np.random.default_rng(0)
    space = model.observation_space
    obs = [{k: rng.normal(0, 1, (2, *s.shape)).astype(np.float32) for k, s in space.spaces.items()} for _ in range(12)]
    starts = np.zeros((12, 2), bool)
    starts[0] = True
    starts[5, 0] = True

    def roll(sequence: list[dict], episode_starts: np.ndarray) -> tuple[list[np.ndarray], list[tuple]]:
        state, actions, states = None, [], []
        for o, s in zip(sequence, episode_starts):
            a, state = model.predict(o, state=state, episode_start=s, deterministic=True)
            actions.append(a)
            states.append(state)
        return actions, states

    actions, states = roll(obs, starts)
    fresh, fresh_states = roll(obs[5:], np.vstack([[True, True], starts[6:]]))
    carried, _ = roll(obs, np.vstack([starts[:1], np.zeros((11, 2), bool)]))
    for t in range(5, 12):  # agent 0 from step 5 on acts as a policy that never saw steps 0-4
        np.testing.assert_allclose(actions[t][0], fresh[t - 5][0], atol=1e-6)
        np.testing.assert_allclose(states[t][0][:, 0], fresh_states[t - 5][0][:, 0], atol=1e-6)
        np.testing.assert_allclose(actions[t][1], carried[t][1], atol=1e-6)  # agent 1 kept its memory
    assert np.abs(carried[5][0] - actions[5][0]).max() > 1e-6  # and the memory did matter
    assert np.abs(fresh[0][1] - actions[5][1]).max() > 1e-6


class Spy:
    """A recurrent model whose ``predict`` calls are recorded."""

    def __init__(self, model) -> None:
        self.model, self.policy, self.calls = model, model.policy, []

    def predict(self, obs, state=None, episode_start=None, deterministic=False):
        self.calls.append((None if state is None else state[0].copy(), np.array(episode_start)))
        return self.model.predict(obs, state=state, episode_start=episode_start, deterministic=deterministic)


def test_evaluate_resets_each_agent_at_its_episode_end(trained: Path) -> None:
    env = hover_env(seed=3, max_steps=12)
    try:
        model, env = load_policy(trained / "final.zip", env)
        spy = Spy(model)
        dones_seen: list[np.ndarray] = []
        step = env.step

        def recording_step(actions):
            result = step(actions)
            dones_seen.append(np.array(result[2], bool))
            return result

        env.step = recording_step
        stats = evaluate(spy, env, episodes=4, deterministic=True, seed=3)
    finally:
        env.close()
    assert stats.episodes == 4
    assert spy.calls[0][0] is None and spy.calls[0][1].all()  # a zero state for every agent after the reset
    for (state, start), done in zip(spy.calls[1:], dones_seen):
        np.testing.assert_array_equal(start, done)  # reset exactly the agents whose episode ended
        assert state is not None and state.shape == (1, 2, RECURRENT_HIDDEN)
    assert any(d.any() for d in dones_seen[:-1])


def test_runner_matches_the_torch_lstm_policy(trained: Path) -> None:
    from sb3_contrib import RecurrentPPO

    # larger actions than a fresh policy's (std 0.01 init), so that clipping to [-1, 1] shows
    model = RecurrentPPO.load(trained / "final.zip", device="cpu")
    with torch.no_grad():
        model.policy.action_net.weight.normal_(0.0, 1.0, generator=torch.Generator().manual_seed(5))
    checkpoint = trained / "scaled.zip"
    model.save(checkpoint)
    shutil.copy(trained / "final.norm.npz", trained / "scaled.norm.npz")
    out = trained / "policy.onnx"
    assert main(["export", "hover", "--checkpoint", str(checkpoint), "--out", str(out)]) == 0
    meta = read_metadata(out)
    assert meta["recurrent"] and meta["recurrent_core"]["units"] == RECURRENT_HIDDEN
    assert [i["name"] for i in meta["inputs"]][-1] == "hidden_in" and meta["inputs"][-1]["shape"] == [2, 1, RECURRENT_HIDDEN]
    env = hover_env(seed=4, max_steps=20)  # episodes end within the 50 steps
    try:
        model, env = load_policy(checkpoint, env)
        raw, expected, hidden, starts = [], [], [], []
        obs, state, start = env.reset(), None, np.ones(2, bool)
        for _ in range(50):
            raw.append(env.get_original_obs())
            starts.append(start)
            action, state = model.predict(obs, state=state, episode_start=start, deterministic=True)
            expected.append(action)
            hidden.append(LstmCore.pack(state))
            obs, _, dones, _ = env.step(action)
            start = np.asarray(dones, bool)
    finally:
        env.close()
    starts = np.stack(starts)
    assert starts[1:].any()  # the state is reset mid-sequence
    observations = {k: np.stack([o[k] for o in raw]) for k in raw[0]}
    np.savez(trained / "observations.npz", episode_start=starts, **observations)
    run_runner(str(out), "--observations", str(trained / "observations.npz"), "--out", str(trained / "actions.npz"))
    with np.load(trained / "actions.npz") as data:
        actions = data["action"]
    expected = np.stack(expected)
    assert actions.shape == expected.shape == (50, 2, 4)
    assert np.any(np.abs(expected) == 1.0) and np.any(np.abs(expected) < 0.99)  # clipped and unclipped actions
    np.testing.assert_allclose(actions, expected, atol=1e-5, rtol=0)
    # the hidden state itself, step by step, through the runner's class
    import importlib.util

    spec = importlib.util.spec_from_file_location("onnx_runner", Path(__file__).resolve().parents[2] / "deploy" / "onnx_runner.py")
    runner = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(runner)
    policy = runner.OnnxPolicy(out)
    assert policy.recurrent and policy.hidden_shape == (2, 1, RECURRENT_HIDDEN)
    for t in range(50):
        if t:
            policy.reset(starts[t])
        np.testing.assert_allclose(policy.act({k: v[t] for k, v in observations.items()}), expected[t], atol=1e-5, rtol=0)
        np.testing.assert_allclose(policy.hidden, hidden[t], atol=1e-5, rtol=0)


def test_bptt_and_shac_refuse_recurrent() -> None:
    for algo in ("bptt", "shac"):
        with pytest.raises(ConfigError, match="recurrent=True is for PPO"):
            TrainConfig(task="hover", algo=algo, recurrent=True).resolved().validate()
    assert main(["train", "hover", "--algo", "bptt", "--recurrent", "--timesteps", "64", "--quiet"]) == 2


def test_training_video_carries_the_lstm_state(trained: Path, tmp_path: Path) -> None:
    from sb3_contrib import RecurrentPPO

    from visfly_dist.training.export import ObsNormalization
    from visfly_dist.training.training_video import TrainingVideo

    model = RecurrentPPO.load(trained / "final.zip", device="cpu")
    video = TrainingVideo("hover", tmp_path, every=100, env_settings={"seed": 0}, max_steps=8)
    try:
        assert video.maybe_record(100, model.policy, ObsNormalization.load(trained / "final.norm.npz"))
        assert video.wait(timeout=300)
    finally:
        video.close()
    assert not video.errors, video.errors
    assert video.written == [tmp_path / "videos" / "step-100.gif"]
    assert video._lstm_state is not None  # the film went through the recurrent branch, which carries the state
    h, c = video._lstm_state
    assert h.shape == (1, 1, RECURRENT_HIDDEN) and np.abs(h).max() > 0
