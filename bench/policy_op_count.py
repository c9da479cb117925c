"""ATen operations in the navigation policy's passes, the phase form of the first layer against the plain one.

    python bench/policy_op_count.py [--batch 64]

On a GPU every operation is at least one kernel launch, and at the rollout's and update's batch
sizes the image trunk is launch-bound, so the count decides between the two forms there. Counted on
the CPU (the count does not depend on the device): a minibatch's forward and backward pass
(``evaluate_actions``, as the PPO update runs it) and a forward pass without gradients.
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3 import PPO
from torch.utils._python_dispatch import TorchDispatchMode

from visfly_dist.training import conv_pool
from visfly_dist.training.extractors import visfly_policy_kwargs


class OperationCount(TorchDispatchMode):
    """Counts the ATen operations dispatched while it is active."""

    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        self.count += 1
        return func(*args, **(kwargs or {}))


def counts(policy: Any, obs: dict[str, torch.Tensor], actions: torch.Tensor) -> tuple[int, int]:
    """(forward and backward of the update, forward without gradients) operation counts."""
    with OperationCount() as update:
        values, log_prob, entropy = policy.evaluate_actions(obs, actions)
        (values.sum() + log_prob.sum() + entropy.sum()).backward()
    with torch.no_grad(), OperationCount() as rollout:
        policy(obs)
    return update.count, rollout.count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=64)
    args = parser.parse_args()
    space = spaces.Dict({"depth": spaces.Box(0.0, 20.0, (1, 64, 64), np.float32),
                         "state": spaces.Box(-np.inf, np.inf, (13,), np.float32),
                         "target": spaces.Box(-np.inf, np.inf, (4,), np.float32)})
    model = PPO("MultiInputPolicy", None, policy_kwargs=visfly_policy_kwargs(), device="cpu", seed=0,
                _init_setup_model=False)
    model.observation_space, model.action_space, model.n_envs = space, spaces.Box(-1, 1, (4,), np.float32), 1
    model._setup_model()
    n = args.batch
    obs = {"depth": torch.rand(n, 1, 64, 64) * 20, "state": torch.randn(n, 13), "target": torch.randn(n, 4)}
    actions = torch.rand(n, 4) * 2 - 1
    phase = counts(model.policy, obs, actions)
    conv_pool.PHASE_MAX_IN_CHANNELS = 0  # the plain convolution and pool for every layer
    plain = counts(model.policy, obs, actions)
    print(f"update forward+backward: phase form {phase[0]}, plain {plain[0]}")
    print(f"forward without gradients: phase form {phase[1]}, plain {plain[1]}")


if __name__ == "__main__":
    main()
