"""Landing: a scripted descent lands by the task's own rule, both cameras, the spawn curriculum and
the differentiable reward."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from visfly_dist import make_env
from visfly_dist.dynamics.rotations import quat_to_rotmat
from visfly_dist.errors import ConfigError
from visfly_dist.tasks.landing import CURRICULUM_WINDOW, DOWNWARD_DEPTH, DOWNWARD_RGB, LandingConfig, shaped_reward
from visfly_dist.tasks.outcomes import end_cause
from visfly_dist.training.config import TrainConfig
from visfly_dist.training.evaluation import eval_config
from tests.tasks.helpers import hover, place, small


def landing_env(camera="rgb", **changes):
    cam = DOWNWARD_RGB if camera == "rgb" else DOWNWARD_DEPTH
    return make_env("landing", num_envs=2, seed=3, camera=camera, **small((cam,)), **changes)


def descend(env):
    """A state-based CTBR controller: track a velocity toward the aim point 0.1 m above the pad,
    descending at 0.15 m/s + 0.8 /s * height (at most 1.5 m/s), so it slows to about 0.2 m/s at the pad."""
    s = env.state
    err = env.pad + torch.tensor([0.0, 0.0, 0.1]) - s.pos
    v_des = torch.cat((err[:, :2].clamp(-0.8, 0.8), -(0.15 + 0.8 * (-err[:, 2:]).clamp(min=0)).clamp(max=1.5)), dim=1)
    accel = 3.0 * (v_des - s.vel) + torch.tensor([0.0, 0.0, 9.81])
    rot = quat_to_rotmat(s.quat)
    z_body, z_want = rot[:, :, 2], accel / accel.norm(dim=1, keepdim=True)
    rates = torch.einsum("nji,nj->ni", rot, 6.0 * torch.cross(z_body, z_want, dim=1))  # world -> body
    ctrl = env.quad.controller
    collective = (accel * z_body).sum(dim=1, keepdim=True)
    return torch.cat((2 * collective / ctrl.max_collective - 1, rates[:, :2] / ctrl.max_rate, torch.zeros_like(collective)),
                     dim=1).clamp(-1, 1).numpy()


def test_a_scripted_descent_from_the_full_spawn_box_lands_by_the_tasks_own_rule():
    with landing_env(curriculum_levels=0) as env:
        env.reset()
        starts, causes = [float(env.state.pos[:, 2].max())], []
        while len(causes) < 6:
            _, reward, done, infos = env.step(descend(env))
            for i in np.flatnonzero(done):
                causes.append(end_cause(infos[i], infos[i]["episode"]["l"], env.config.max_episode_steps))
                assert reward[i] > 9  # the success bonus
            if done.any():
                starts.append(float(env.state.pos[:, 2].max()))
    assert causes == ["success"] * 6
    assert max(starts) > 1.5  # it started from the full box, not an easy one


@pytest.mark.parametrize("camera", ["rgb", "depth"])
def test_both_cameras_give_their_image_and_agree_on_where_the_pad_is(camera):
    with landing_env(camera) as env:
        obs = env.reset()
        image = "color" if camera == "rgb" else "depth"
        assert set(obs) == {"state", "pad", image} and set(env.observation_space.spaces) == set(obs)
        for key, value in obs.items():
            assert env.observation_space[key].contains(value[0]), key
        place(env, [[2.4, 0.3, 1.5], [5.0, 0.0, 1.5]])  # off-centre over the pad; 3 m beside it
        obs, *_ = env.step(hover(env))
        if camera == "depth":
            assert obs["depth"][0].min() == pytest.approx(1.49, abs=0.05)  # the floor, 1.5 m below
        seen, lost = obs["pad"]
        # Camera image x is body -y, image y is body -x: the pad lies behind-right of the drone.
        assert seen[0] == pytest.approx(0.2, abs=0.08) and seen[1] == pytest.approx(0.27, abs=0.08) and seen[2] > 0
        assert lost.tolist() == [0, 0, 0]


def test_camera_settings_are_checked():
    with pytest.raises(ConfigError, match=r"camera='ir' must be one of \['rgb', 'depth'\]"):
        LandingConfig(camera="ir").validate()
    with pytest.raises(ConfigError, match="camera='depth' needs a depth camera first in cameras"):
        LandingConfig(camera="depth", cameras=(DOWNWARD_RGB,)).validate()
    assert LandingConfig(camera="depth").cameras == (DOWNWARD_DEPTH,)
    with pytest.raises(ConfigError, match=r"curriculum_levels=-1 must be an int >= 0.*curriculum_start=0 must be"):
        LandingConfig(curriculum_levels=-1, curriculum_start=0).validate()


def test_the_spawn_box_grows_a_level_each_time_half_the_last_64_episodes_landed_and_evaluation_starts_full():
    with landing_env(curriculum_levels=2, curriculum_start=0.2) as env:
        env.reset()
        every = torch.arange(2)
        heights = lambda: torch.cat([env.spawn_positions(every) for _ in range(20)])[:, 2] - env.pad[0, 2]  # noqa: E731

        def episodes(landed):  # 2 agents end an episode each step: slowly just above the pad, or 2 m/s into it
            for _ in range(CURRICULUM_WINDOW // 2):
                place(env, np.add(env.pad.numpy(), [0.0, 0.0, 0.15]))
                env.state = dataclasses.replace(env.state, vel=torch.tensor([[0.0, 0.0, -0.1 if landed else -2.0]] * 2))
                _, _, done, _ = env.step(hover(env))
                assert done.all()

        assert env.spawn_scale() == pytest.approx(0.2) and float(heights().max()) <= 0.7 + 1e-6
        episodes(landed=False)
        assert env.curriculum_level == 0  # 64 crashes: no promotion
        episodes(landed=True)
        assert env.curriculum_level == 1 and env.spawn_scale() == pytest.approx(0.6)
        assert float(heights().max()) <= 0.6 * 3.5 + 1e-6
        episodes(landed=True)
        assert env.spawn_scale() == 1.0 and float(heights().max()) > 2.2  # the full 1.5-3.5 m box
    run = TrainConfig(task="landing", overrides={"curriculum_levels": 5})
    assert eval_config("landing", 12345, run, {}, {}).overrides["curriculum_levels"] == 0
    assert eval_config("landing", 12345, run, {"curriculum_levels": 7}, {}).overrides["curriculum_levels"] == 7


def test_the_shaped_reward_matches_finite_differences_and_pays_a_slow_final_approach():
    torch.manual_seed(0)
    aim, prev = torch.tensor([[2.0, 0.0, 0.1]] * 3, dtype=torch.float64), torch.full((3,), 2.0, dtype=torch.float64)
    pos = (aim + torch.tensor([0.0, 0.0, 1.5]) + 0.3 * torch.randn(3, 3, dtype=torch.float64)).requires_grad_()
    vel = (2.0 * torch.randn(3, 3, dtype=torch.float64)).requires_grad_()
    omega = torch.randn(3, 3, dtype=torch.float64).requires_grad_()

    def reward(pos, vel, omega):
        return shaped_reward(pos, vel, omega, aim, prev, torch.ones(3, dtype=torch.float64), 0.03, 0.1, 0.3, 0.5, 0.5)

    assert torch.autograd.gradcheck(reward, (pos, vel, omega), eps=1e-6, atol=1e-6)
    # 0.3 m above the aim point, descending: 0.3 m/s earns more than 2 m/s, which is over 0.3 + 0.5 * 0.3.
    at = aim[:2] + torch.tensor([0.0, 0.0, 0.3], dtype=torch.float64)
    slow_fast = torch.tensor([[0.0, 0.0, -0.3], [0.0, 0.0, -2.0]], dtype=torch.float64)
    step = at + slow_fast * 0.03
    r = shaped_reward(step, slow_fast, torch.zeros(2, 3, dtype=torch.float64), aim[:2], torch.full((2,), 0.3, dtype=torch.float64),
                      torch.ones(2, dtype=torch.float64), 0.03, 0.1, 0.3, 0.5, 0.5)
    assert r[0] > r[1]
    # Descending at 0.5 m/s 1 m beside the pad earns 0.5 * 0.5 * 0.8 less than over it; hovering there costs nothing.
    beside = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [1.0, 0.0, 1.0]], dtype=torch.float64) + aim
    vel = torch.tensor([[0.0, 0.0, -0.5], [0.0, 0.0, -0.5], [0.0, 0.0, 0.0]], dtype=torch.float64)
    r = shaped_reward(beside, vel, torch.zeros(3, 3, dtype=torch.float64), aim, (beside - aim).norm(dim=1),
                      torch.ones(3, dtype=torch.float64), 0.03, 1.0, 0.2, 0.5, 0.5)
    assert r[1] == pytest.approx(r[0] - 0.2, abs=1e-9) and r[2] > r[1]


def test_depth_landing_reward_carries_gradients_through_the_dynamics():
    cams = (dataclasses.replace(DOWNWARD_DEPTH, width=16, height=16),)
    for reward in ("ours", "visfly"):
        with make_env("landing", num_envs=1, camera="depth", cameras=cams, reward=reward, requires_grad=True,
                      **small()) as env:
            env.reset()
            action = torch.zeros(1, 4, requires_grad=True)
            total = sum(env.step_tensor(action).reward.sum() for _ in range(3))
            (grad,) = torch.autograd.grad(total, action)
        assert torch.isfinite(grad).all() and float(grad.abs().sum()) > 0, reward
