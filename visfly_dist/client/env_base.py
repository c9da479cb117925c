"""``DroneEnvBase``: the base class of every task, a tensor env that is also an SB3 ``VecEnv``.

A task subclasses it and writes only its hooks:

- ``get_observation() -> dict[str, Tensor]`` (one entry per ``observation_space_dict`` key),
- ``get_reward() -> Tensor (N,)``, ``get_success() -> bool Tensor (N,)``,
- optionally ``get_failure()`` (default: collision, inside an obstacle or out of bounds),
  ``observation_space_dict()``, ``spawn_distribution()`` / ``spawn_positions(idx)``,
  ``reset_agents_hook(idx)``.

The state, the step and the resets are the core's (:mod:`visfly_dist.client.core`:
``step_tensor``, ``send``/``recv``, ``reset_tensor``); the SB3 interface is the adapter's
(:mod:`visfly_dist.client.sb3`: the terminal observation goes into ``info["terminal_observation"]``);
``as_gymnasium()`` gives the Gymnasium views (:mod:`visfly_dist.client.gym_view`).
"""

from __future__ import annotations

from typing import Any

from visfly_dist.client.core import PROBE_CAMERA, STATE_DIM, Spawn, StepResult, camera_space, combined_seed
from visfly_dist.client.sb3 import SB3VecEnv

__all__ = ["DroneEnvBase", "PROBE_CAMERA", "STATE_DIM", "Spawn", "StepResult", "camera_space", "combined_seed"]


class DroneEnvBase(SB3VecEnv):
    """Base class of every task: the tensor env's dynamics, aggregator, noise and resets
    (:class:`~visfly_dist.client.core.TensorEnv`) with the SB3 ``VecEnv`` interface."""

    def as_gymnasium(self, autoreset_mode: Any = None):
        """This env as a ``gymnasium.vector.VectorEnv`` (NEXT_STEP autoreset unless told otherwise); shares this env."""
        from gymnasium.vector import AutoresetMode

        from visfly_dist.client.gym_view import GymnasiumVectorView

        return GymnasiumVectorView(self, autoreset_mode or AutoresetMode.NEXT_STEP)

    def as_gymnasium_env(self):
        """A single-agent ``gymnasium.Env`` over this env (needs ``num_envs == 1``), e.g. for ``check_env``."""
        from visfly_dist.client.gym_view import SingleAgentView

        return SingleAgentView(self)
