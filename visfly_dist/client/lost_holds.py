"""How long agents whose worker failed are held before their episode is cut (pure, time passed in).

An agent with no fresh observation (``lost``: its worker died, hung or restarted) is held: the env
undoes its step and it waits where it was while its scene moves to another worker. A hold lasts at
most ``limit_s`` from the first step the agent was lost; then its episode is cut once (truncated,
``lost``), and if the worker is still away the next episode is held again. A step that serves the
agent ends its hold.
"""

from __future__ import annotations

import numpy as np

__all__ = ["LostHolds"]


class LostHolds:
    """Per agent, since when it has been lost (NaN: served).

    Args:
        num_agents: agents of the env.
        limit_s: the longest hold, seconds (0: cut at once, no hold).
    """

    def __init__(self, num_agents: int, limit_s: float) -> None:
        self.limit_s = float(limit_s)
        self._since = np.full(num_agents, np.nan)
        self._any = False  # some agent is being held (a served step checks nothing otherwise)

    def update(self, stepped: np.ndarray, lost: np.ndarray, now: float) -> np.ndarray:
        """The agents held this step (``(N,)`` bool).

        Args:
            stepped: ``(N,)`` bool, the agents of this step.
            lost: ``(N,)`` bool, those of them with no fresh observation.
            now: the clock, seconds (``time.monotonic()``).
        """
        since = self._since
        since[stepped & ~lost] = np.nan
        since[lost & np.isnan(since)] = now
        expired = lost & (now - since >= self.limit_s)
        since[expired] = np.nan
        self._any = not np.isnan(since).all()
        return lost & ~expired

    def served(self, agents: np.ndarray) -> None:
        """``agents`` were all served this step: their holds end (cheap when none was held)."""
        if self._any and not np.isnan(self._since[agents]).all():
            self._since[agents] = np.nan
            self._any = not np.isnan(self._since).all()
