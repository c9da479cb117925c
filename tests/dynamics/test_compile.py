"""``torch.compile`` of the control step gives the eager answer (slow: compiling takes ~30 s)."""

from __future__ import annotations

import pytest
import torch

from visfly_dist.dynamics import DynamicsConfig, Quadrotor


@pytest.mark.slow
def test_compiled_step_matches_eager():
    settings = dict(controller="ctbr", ctrl_dt=0.01, sim_dt=0.01, integrator="euler")
    eager = Quadrotor(DynamicsConfig(**settings), num_agents=4)
    compiled = Quadrotor(DynamicsConfig(**settings, compile=True), num_agents=4)
    a = b = eager.initial_state(pos=torch.ones(4, 3))
    action = eager.hover_action() + 0.2 * torch.rand(4, 4, generator=torch.Generator().manual_seed(0)) - 0.1
    for _ in range(5):
        a, b = eager.step(a, action), compiled.step(b, action)
    assert torch.allclose(a.pos, b.pos, atol=1e-6) and torch.allclose(a.quat, b.quat, atol=1e-6)
