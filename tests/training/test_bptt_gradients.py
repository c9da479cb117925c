"""The differentiable window: its gradient against finite differences (float64), the discount reset,
the SHAC bootstrap, lost agents, TD(lambda) targets, and gradients through the real hover env."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from visfly_dist.dynamics import DynamicsConfig, QuadState, Quadrotor
from visfly_dist.tasks import make_env
from visfly_dist.training.diff_common import Critic, DiffActor, Window, rollout_window
from visfly_dist.training.shac import lambda_returns, scale_gradient

F64 = torch.float64
TARGET = torch.tensor([0.5, -0.2, 1.5], dtype=F64)


class StateOnly(nn.Module):
    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        return obs["state"]


class HoverStub:
    """A float64 hover task on the real dynamics, with the env's conventions: episodes of
    ``length`` steps end truncated, the agent is reset by ``QuadState.where`` (cutting its
    gradient), ``info`` carries ``terminal_observation``, ``lost`` (agent ``lose`` at step
    ``lose_at``), ``success`` and the episode statistics."""

    def __init__(self, n: int = 3, length: int = 4, lose_at: int | None = None, lose: int = 1) -> None:
        self.num_envs, self.length, self.lose_at, self.lose = n, length, lose_at, lose
        self.quad = Quadrotor(DynamicsConfig(controller="ctbr"), num_agents=n, dtype=F64)
        start = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.5, 2.0], [-0.5, 0.3, 1.2]], dtype=F64)[:n]
        self.fresh = self.quad.initial_state(pos=start, vel=torch.full((n, 3), 0.3, dtype=F64))
        self.state = self.fresh
        self.t = torch.zeros(n, dtype=torch.long)
        self.calls = 0
        self.returns = torch.zeros(n, dtype=F64)

    def observe(self) -> dict[str, torch.Tensor]:
        s = self.state
        return {"state": torch.cat((s.pos - TARGET, s.vel, s.quat, s.omega), dim=1)}

    def step_tensor(self, action: torch.Tensor):
        self.state = self.quad.step(self.state, action)
        self.t = self.t + 1
        reward = 1.0 - 0.5 * (self.state.pos - TARGET).norm(dim=1) - 0.05 * self.state.vel.norm(dim=1)
        self.returns = self.returns + reward.detach()
        lost = torch.zeros(self.num_envs, dtype=torch.bool)
        if self.calls == self.lose_at:
            lost[self.lose] = True
        self.calls += 1
        truncated = (self.t >= self.length) | lost
        terminal = self.observe()
        info = {"terminal_observation": terminal, "lost": lost, "held": torch.zeros_like(lost), "success": torch.zeros_like(lost),
                "episode_return": self.returns.clone(), "episode_length": self.t.clone()}
        self.state = QuadState.where(truncated, self.fresh, self.state)
        self.t = torch.where(truncated, 0, self.t)
        self.returns = torch.where(truncated, 0.0, self.returns)
        return self.observe(), reward, torch.zeros_like(lost), truncated, info


def make_actor() -> DiffActor:
    torch.manual_seed(0)
    return DiffActor(None, extractor=StateOnly(), features_dim=13).double()


def window_loss(actor: DiffActor, value=None, horizon: int = 7, **stub) -> Window:
    env = HoverStub(**stub)
    return rollout_window(env, actor, env.observe(), horizon, gamma=0.9, value=value)


def quadratic_value(obs: dict[str, torch.Tensor]) -> torch.Tensor:
    return 5.0 - obs["state"][:, :6].square().sum(dim=1)


@pytest.mark.parametrize("value", [None, quadratic_value], ids=["bptt", "shac"])
def test_window_gradient_matches_finite_differences(value):
    actor = make_actor()
    params = list(actor.parameters())
    grads = torch.autograd.grad(window_loss(actor, value).loss, params)
    g = torch.Generator().manual_seed(1)
    directions = [torch.randn(p.shape, generator=g, dtype=F64) for p in params]
    eps = 1e-6

    def moved(d: float) -> float:
        with torch.no_grad():
            for p, u in zip(params, directions):
                p.add_(d * u)
            loss = float(window_loss(actor, value).loss)
            for p, u in zip(params, directions):
                p.sub_(d * u)
        return loss

    analytic = sum(float((gr * u).sum()) for gr, u in zip(grads, directions))
    fd = (moved(eps) - moved(-eps)) / (2 * eps)
    assert analytic != 0.0
    assert analytic == pytest.approx(fd, rel=1e-6, abs=1e-9)


def test_discount_restarts_after_a_done_and_the_reset_cuts_the_gradient():
    """Episodes of 4 steps in a 7-step window: the loss is the discounted sum per episode."""
    actor = make_actor()
    window = window_loss(actor, horizon=7, length=4)
    r = window.rewards
    weights = torch.tensor([1, 0.9, 0.81, 0.729, 1, 0.9, 0.81], dtype=F64)
    assert window.steps == 7 and window.done[3].all() and not window.done[4:].any()
    assert float(window.loss.detach()) == pytest.approx(float(-(weights[:, None] * r).sum() / (7 * 3)), rel=1e-12)
    # The first action of agent 0 reaches no reward after its reset.
    env = HoverStub(length=2)
    obs = env.observe()
    first = actor(obs)
    a0 = first.detach().requires_grad_()
    obs, r0, *_ = env.step_tensor(a0)
    obs, r1, *_ = env.step_tensor(actor(obs))
    obs, r2, *_ = env.step_tensor(actor(obs))        # first step of the second episode
    (g_late,) = torch.autograd.grad(r2.sum(), a0, retain_graph=True, allow_unused=True)
    (g_early,) = torch.autograd.grad(r1.sum(), a0)
    assert (g_late is None or float(g_late.abs().max()) == 0.0) and float(g_early.abs().max()) > 0.0


def test_a_lost_agent_ends_the_window_without_its_reward():
    actor = make_actor()
    window = window_loss(actor, horizon=8, lose_at=2, lose=1, length=100)
    assert window.steps == 3 and window.lost_agents == 1
    assert window.rewards[2, 1] == 0.0 and window.rewards[2, 0] != 0.0
    assert not window.valid[2, 1] and window.valid[:2].all() and window.done[2, 1]
    params = list(actor.parameters())
    grads = torch.autograd.grad(window.loss, params)
    assert all(torch.isfinite(g).all() for g in grads)


def test_shac_bootstrap_adds_the_end_value():
    actor = make_actor()
    plain = window_loss(actor, horizon=3, length=100)
    boot = window_loss(actor, quadratic_value, horizon=3, length=100)
    end = quadratic_value(detach(plain.next_obs))
    expected = float(plain.loss.detach()) - float((0.9 ** 3 * end).sum()) / (3 * 3)
    assert float(boot.loss.detach()) == pytest.approx(expected, rel=1e-10)
    torch.testing.assert_close(boot.next_values[-1], end)


def detach(obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: v.detach() for k, v in obs.items()}


def test_lambda_returns_cut_at_dones_and_at_the_window_end():
    rewards = torch.tensor([[1.0], [2.0], [3.0]])
    done = torch.tensor([[False], [True], [False]])
    next_values = torch.tensor([[0.0], [10.0], [20.0]])      # truncated at t=1 -> V(terminal) = 10
    values = torch.tensor([[5.0], [6.0], [7.0]])
    window = Window(loss=torch.tensor(0.0), steps=3, obs=[], rewards=rewards, done=done, next_values=next_values,
                    valid=torch.ones_like(done), next_obs={})
    gamma, lam = 0.5, 0.8
    g2 = 3.0 + gamma * 20.0
    g1 = 2.0 + gamma * 10.0
    g0 = 1.0 + gamma * ((1 - lam) * 6.0 + lam * g1)
    torch.testing.assert_close(lambda_returns(window, values, gamma, lam), torch.tensor([[g0], [g1], [g2]]))


def test_critic_scale_is_the_running_mean_and_variance_of_its_targets():
    from gymnasium import spaces
    critic = Critic(spaces.Dict({"state": spaces.Box(-1, 1, (13,))}))
    batches = [torch.randn(50) * 30 + 60, torch.randn(70) * 5 - 10, torch.randn(20) + 100]
    for b in batches:
        critic.update_scale(b)
    every = torch.cat(batches)
    torch.testing.assert_close(critic.mean, every.mean())
    torch.testing.assert_close(critic.var, every.var(unbiased=False))
    obs = {"state": torch.randn(4, 13)}
    torch.testing.assert_close(critic(obs), critic.mean + critic.var.sqrt() * critic.normalized(obs))
    torch.testing.assert_close(critic.normalize(critic(obs)), critic.normalized(obs))


def test_scale_gradient_keeps_the_value_and_scales_the_gradient():
    x = torch.tensor([1.0, -2.0], requires_grad=True)
    y = scale_gradient(x * 3, 0.25)
    torch.testing.assert_close(y, torch.tensor([3.0, -6.0]))
    (grad,) = torch.autograd.grad(y.sum(), x)
    torch.testing.assert_close(grad, torch.tensor([0.75, 0.75]))


def test_real_hover_and_landing_rewards_carry_gradients_to_the_actions():
    for task, settings in (("hover", {}), ("landing", {"max_episode_steps": 50})):
        env = make_env(task, num_envs=2, requires_grad=True, seed=0, **settings)
        try:
            env.reset()
            action = torch.zeros(2, 4, requires_grad=True)
            total = 0
            for _ in range(3):
                _, reward, *_ = env.step_tensor(action)
                total = total + reward.sum()
            (grad,) = torch.autograd.grad(total, action)
            assert torch.isfinite(grad).all() and float(grad.abs().sum()) > 0, task
        finally:
            env.close()
