"""Small settings for task envs: 16x16 images, one raycast worker."""

from __future__ import annotations

import dataclasses

from visfly_dist.aggregator import PoolConfig


def small(cameras=(), **changes):
    """Overrides for ``make_env``: tiny images of the task's own cameras, one raycast worker."""
    changes.setdefault("pool", PoolConfig(num_local_workers=1, backend="raycast", startup_timeout_s=60.0))
    if cameras:
        changes["cameras"] = tuple(dataclasses.replace(c, width=16, height=16) for c in cameras)
    return changes
