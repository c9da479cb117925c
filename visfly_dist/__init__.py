"""visfly-dist: a distributed simulator for vision-based quadrotor reinforcement learning."""

__version__ = "0.1.0"
