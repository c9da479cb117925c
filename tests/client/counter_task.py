"""A tiny deterministic task (CounterTask) and small env configs shared by the client tests.

Envs start real worker processes (raycast backend); fixtures are module-scoped and closed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from gymnasium import spaces

from visfly_dist.aggregator import PoolConfig
from visfly_dist.client import DroneEnvBase, EnvConfig, Spawn
from visfly_dist.protocol.cameras import CameraSpec

DEPTH = CameraSpec(name="depth", kind="depth", width=16, height=16, far=20.0)


@dataclass
class CounterConfig(EnvConfig):
    scenes: tuple[str, ...] = ("gen:empty",)
    cameras: tuple[CameraSpec, ...] = (DEPTH,)
    max_episode_steps: int = 5
    num_envs: int = 4


def small_pool(workers: int = 1, **changes) -> PoolConfig:
    return PoolConfig(num_local_workers=workers, backend="raycast", startup_timeout_s=60.0, **changes)


class CounterTask(DroneEnvBase):
    """Observation: state, depth, and the episode's step count; reward: height; success on demand."""

    config_class = CounterConfig

    def __init__(self, config: CounterConfig | None = None) -> None:
        super().__init__(config)
        self.force_success = torch.zeros(self.num_envs, dtype=torch.bool)

    def observation_space_dict(self):
        out = super().observation_space_dict()
        out["step"] = spaces.Box(0, np.inf, (1,), np.float32)
        return out

    def spawn_distribution(self) -> Spawn:
        return Spawn.around((0.0, 0.0, 2.0), (1.0, 1.0, 0.5), clearance=0.3)

    def get_observation(self):
        return {"state": self.state_vector(), "step": self.episode_step.float()[:, None], **self.frame.images}

    def get_reward(self):
        return self.state.pos[:, 2]

    def get_success(self):
        return self.force_success.clone()


def make_counter(**changes) -> CounterTask:
    changes.setdefault("pool", small_pool())
    return CounterTask(CounterConfig(**changes))
