"""Vector envs over the distributed simulator: the tensor env core, its SB3 ``VecEnv`` and Gymnasium adapters, noise."""

from visfly_dist.client.config import EnvConfig
from visfly_dist.client.core import TensorEnv
from visfly_dist.client.env_base import DroneEnvBase, Spawn, StepResult
from visfly_dist.client.multi_agent import MultiDroneEnvBase
from visfly_dist.client.noise import NoiseSpec, SensorNoise

__all__ = ["DroneEnvBase", "TensorEnv", "EnvConfig", "MultiDroneEnvBase", "NoiseSpec", "SensorNoise", "Spawn", "StepResult"]
