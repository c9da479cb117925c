"""Shared pieces of the task tests: small settings per task, teleporting agents, the hover action."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from visfly_dist.aggregator import PoolConfig
from visfly_dist.dynamics import QuadState
from visfly_dist.tasks.landing import DOWNWARD_RGB
from visfly_dist.tasks.navigation import FORWARD_DEPTH


def small(cameras=(), **changes):
    """Overrides for ``make_env``: tiny images of the task's own cameras, one raycast worker."""
    changes.setdefault("pool", PoolConfig(num_local_workers=1, backend="raycast", startup_timeout_s=60.0))
    if cameras:
        changes["cameras"] = tuple(dataclasses.replace(c, width=16, height=16) for c in cameras)
    return changes


SETTINGS = {
    "navigation": dict(num_envs=2, **small((FORWARD_DEPTH,), density=0.05)),
    "navigation_moving": dict(num_envs=2, **small((FORWARD_DEPTH,), density=0.05, moving=4)),
    "hover": dict(num_envs=2, **small(target=(0.0, 0.0, 3.0))),  # the scene's goal wins
    "landing": dict(num_envs=2, **small((DOWNWARD_RGB,), camera="rgb")),  # the RGB pad segmentation
    "gap_crossing": dict(num_envs=3, **small((FORWARD_DEPTH,))),
    "racing": dict(num_envs=2, **small()),
    "tracking": dict(num_envs=2, **small((FORWARD_DEPTH,))),
}



def place(env, positions):
    """Teleport every agent (at rest, level) to ``positions``."""
    fresh = env.quad.initial_state(torch.as_tensor(np.asarray(positions, dtype=np.float32)))
    env.state = QuadState.where(torch.ones(env.num_envs, dtype=torch.bool), fresh, env.state)


def hover(env):
    """``(N, 4)`` actions that hold every agent level at hover thrust."""
    return np.tile(env.quad.hover_action().numpy(), (env.num_envs, 1))
