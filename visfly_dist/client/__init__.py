"""Vector envs over the distributed simulator: SB3 ``VecEnv`` base classes, Gymnasium views, noise."""

from visfly_dist.client.config import EnvConfig
from visfly_dist.client.env_base import DroneEnvBase, Spawn, StepResult
from visfly_dist.client.multi_agent import MultiDroneEnvBase
from visfly_dist.client.noise import NoiseSpec, SensorNoise

__all__ = ["DroneEnvBase", "EnvConfig", "MultiDroneEnvBase", "NoiseSpec", "SensorNoise", "Spawn", "StepResult"]
