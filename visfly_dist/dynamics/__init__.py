"""Batched, differentiable quadrotor dynamics in pure torch (no I/O; of visfly-dist only ``errors``).

    quad = Quadrotor(DynamicsConfig(controller="ctbr"), load_airframe("visfly"), num_agents=N)
    state = quad.initial_state(pos=...)
    state = quad.step(state, action)          # action (N, 4) in [-1, 1]
"""

from visfly_dist.dynamics.airframe import Airframe, ControllerGains, list_airframes, load_airframe
from visfly_dist.dynamics.config import CONTROLLERS, INTEGRATORS, DynamicsConfig
from visfly_dist.dynamics.quadrotor import Quadrotor
from visfly_dist.dynamics.sampler import Distribution, InitialSample, InitialStateSampler
from visfly_dist.dynamics.state import QuadState

__all__ = [
    "Airframe", "ControllerGains", "list_airframes", "load_airframe",
    "CONTROLLERS", "INTEGRATORS", "DynamicsConfig",
    "Quadrotor", "QuadState",
    "Distribution", "InitialSample", "InitialStateSampler",
]
