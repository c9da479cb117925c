"""The rollout's policy forward from CUDA graphs against the eager forward.

The CUDA tests run where torch sees a GPU (the GPU host's round runs this file); on a CPU the
forward must be the policy's own call.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gymnasium import spaces
from stable_baselines3.common.policies import MultiInputActorCriticPolicy

from visfly_dist.training import graphed_policy
from visfly_dist.training.extractors import visfly_policy_kwargs
from visfly_dist.training.graphed_policy import GraphedForward

SPACE = spaces.Dict({"depth": spaces.Box(0.0, 10.0, (1, 64, 64), np.float32),
                     "state": spaces.Box(-np.inf, np.inf, (13,), np.float32)})
cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU torch can use")


def _policy(device: str) -> MultiInputActorCriticPolicy:
    torch.manual_seed(0)
    policy = MultiInputActorCriticPolicy(SPACE, spaces.Box(-1, 1, (4,), np.float32), lambda _: 3e-4,
                                         **visfly_policy_kwargs())
    return policy.to(device).eval()


def _obs(n: int, device: str, seed: int = 1) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {"depth": (torch.rand((n, 1, 64, 64), generator=g) * 10).to(device),
            "state": torch.randn((n, 13), generator=g).to(device)}


def test_cpu_forward_is_the_policys_own() -> None:
    policy, obs = _policy("cpu"), _obs(8, "cpu")
    forward = GraphedForward(policy)
    with torch.no_grad():
        torch.manual_seed(5)
        actions, values, log_probs = forward(obs)
        torch.manual_seed(5)
        eager = policy(obs)
    assert torch.equal(actions, eager[0]) and torch.equal(values, eager[1]) and torch.equal(log_probs, eager[2])
    assert not forward._graphs


@cuda
def test_graph_matches_the_eager_policy_and_follows_its_weights() -> None:
    policy, obs = _policy("cuda"), _obs(64, "cuda")
    forward = GraphedForward(policy, log=pytest.fail)
    with torch.no_grad():
        actions, values, log_probs = forward(obs)
        assert len(forward._graphs) == 1
        expected_values, expected_log_probs, _ = policy.evaluate_actions(obs, actions)
        torch.testing.assert_close(values, expected_values, rtol=1e-4, atol=1e-5)
        torch.testing.assert_close(log_probs, expected_log_probs, rtol=1e-4, atol=1e-4)
        again, _, _ = forward(obs)
        assert not torch.equal(actions, again), "every replay draws fresh noise"
        policy.value_net.bias.add_(1.0)  # as an optimizer step does: in place
        shifted = forward(obs)[1]
        torch.testing.assert_close(shifted, expected_values + 1.0, rtol=1e-4, atol=1e-5)
        other = _obs(64, "cuda", seed=2)
        torch.testing.assert_close(forward(other)[1], policy.predict_values(other), rtol=1e-4, atol=1e-5)
        forward(_obs(32, "cuda"))
    assert len(forward._graphs) == 2, "one graph per batch size"
    assert torch.distributions.Distribution._validate_args, "the capture leaves torch's checks as they were"


@cuda
def test_graph_follows_every_parameter_updated_in_place() -> None:
    """Every parameter moved in place is seen by the next replay (a kernel kept on the Python side
    once froze the first convolution of the rollout's policy at its capture)."""
    policy, obs = _policy("cuda"), _obs(64, "cuda")
    forward = GraphedForward(policy, log=pytest.fail)
    g = torch.Generator(device="cuda").manual_seed(7)
    with torch.no_grad():
        forward(obs)
        for parameter in policy.parameters():  # an optimizer step, roughly: everything moves in place
            parameter.add_(0.05 * torch.randn(parameter.shape, device="cuda", generator=g))
        actions, values, log_probs = forward(obs)
        expected_values, expected_log_probs, _ = policy.evaluate_actions(obs, actions)
    torch.testing.assert_close(values, expected_values, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(log_probs, expected_log_probs, rtol=1e-4, atol=1e-4)
    assert forward.verify() and forward._graphs


@cuda
def test_verify_drops_graphs_that_read_stale_parameters() -> None:
    policy, lines = _policy("cuda"), []
    forward = GraphedForward(policy, log=lines.append)
    with torch.no_grad():
        forward(_obs(16, "cuda"))
        assert forward.verify()
        policy.value_net.weight.data = policy.value_net.weight.data + 1.0  # new storage: the graph reads the old one
        assert not forward.verify()
        assert not forward._graphs and forward.disabled and len(lines) == 1
        torch.testing.assert_close(forward(_obs(16, "cuda"))[1], policy.predict_values(_obs(16, "cuda")))


@cuda
def test_outputs_outlive_the_next_replay() -> None:
    policy = _policy("cuda")
    forward = GraphedForward(policy, log=pytest.fail)
    with torch.no_grad():
        values = forward(_obs(16, "cuda", seed=3))[1]
        kept = values.clone()
        forward(_obs(16, "cuda", seed=4))
    assert torch.equal(values, kept)


@cuda
def test_disabled_by_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(graphed_policy.DISABLE_ENV, "0")
    forward = GraphedForward(_policy("cuda"))
    with torch.no_grad():
        forward(_obs(8, "cuda"))
    assert not forward._graphs and forward.disabled
