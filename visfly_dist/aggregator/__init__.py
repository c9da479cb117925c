"""The distribution layer between the env and the scene workers: pool, scenes, fan-out, recovery."""

from visfly_dist.aggregator.aggregator import Aggregator, StepTicket
from visfly_dist.aggregator.assembler import Observation
from visfly_dist.aggregator.config import PoolConfig, SceneSetConfig

__all__ = ["Aggregator", "Observation", "PoolConfig", "SceneSetConfig", "StepTicket"]
