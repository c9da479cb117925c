"""PPO on the real hover env: it learns, and a seed reproduces the first rollout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from visfly_dist.training.config import TrainConfig
from visfly_dist.training.evaluation import build_eval_env, evaluate, load_policy
from visfly_dist.training.ppo import build_env, build_model, train


class UniformPolicy:
    """Actions drawn uniformly from ``[-1, 1]^4`` (seeded): the baseline to beat."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def predict(self, obs: dict[str, np.ndarray], deterministic: bool = False) -> tuple[np.ndarray, None]:
        n = len(next(iter(obs.values())))
        return self.rng.uniform(-1.0, 1.0, (n, 4)).astype(np.float32), None


def hover_config(out: Path, **changes) -> TrainConfig:
    settings = dict(task="hover", num_envs=16, workers=1, n_steps=32, batch_size=256, lr=1e-3, n_epochs=5,
                    checkpoint_every=0, progress=False, seed=3, out=str(out))
    settings.update(changes)
    return TrainConfig(**settings)


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["sb3-ppo", "ppo"])
def test_ppo_beats_a_random_policy_on_hover(tmp_path: Path, algo: str) -> None:
    """Both PPO trainers (SB3's loop and the tensor PPO) learn to hover."""
    torch.manual_seed(0)
    result = train(hover_config(tmp_path / "run", timesteps=20_000, algo=algo))
    assert result.final_model.is_file() and not result.interrupted and result.config.algo == algo

    env = build_eval_env("hover", 16, 7, hover_config(tmp_path), {}, {})
    try:
        random_stats = evaluate(UniformPolicy(7), env, episodes=32)
        model, env = load_policy(result.final_model, env)
        env.seed(7)
        trained_stats = evaluate(model, env, episodes=32, deterministic=True)
    finally:
        env.close()
    # Hover pays up to ~1 per step of 100 and -10 on failure; a random CTBR policy tumbles out early.
    assert trained_stats.mean_return > random_stats.mean_return + 15.0, (random_stats, trained_stats)
    assert trained_stats.mean_length > random_stats.mean_length


def first_rollout(cfg: TrainConfig) -> tuple[np.ndarray, np.ndarray]:
    env = build_env(cfg.resolved())
    try:
        model = build_model(cfg.resolved(), env)
        model.learn(cfg.n_steps * cfg.num_envs)
        buf = model.rollout_buffer
        return buf.actions.copy(), buf.rewards.copy()
    finally:
        env.close()


def test_same_seed_same_first_rollout(tmp_path: Path) -> None:
    settings = dict(num_envs=4, n_steps=24, batch_size=48, overrides={"max_episode_steps": 16})
    a = first_rollout(hover_config(tmp_path / "a", **settings))
    b = first_rollout(hover_config(tmp_path / "b", **settings))
    c = first_rollout(hover_config(tmp_path / "c", seed=4, **settings))
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])
