"""The observation assembler: worker replies scattered into buffers allocated before they arrive.

A step request to one worker carries its agents' poses as one array; its reply carries every array
(images per camera, collision, inside, nearest, distance) with the rows in request order. The
assembler knows, per request, which observation row each reply row belongs to, so each reply array
costs one indexed copy (``out[rows] = reply``). Images a worker on this host traced straight into
the step's segment (:mod:`.image_shm`) are already in place: the observation is a view of that
segment, with no copy before it becomes a torch tensor (``torch.from_numpy``). Inline images are
copied once from the received payload (:func:`visfly_dist.protocol.codec.decode`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from visfly_dist.errors import ProtocolError
from visfly_dist.protocol.cameras import CameraSpec

QUERY_FIELDS = ("collision", "inside", "nearest", "distance")


@dataclass
class Observation:
    """What the workers saw for ``k`` agents, in the order they were asked for.

    Attributes:
        images: camera name -> ``(k, C, H, W)`` array of the camera's dtype.
        collision: ``(k,)`` bool, the drone's sphere touches an obstacle.
        inside: ``(k,)`` bool, the drone is inside a closed obstacle.
        nearest: ``(k, 3)`` float32 nearest obstacle point (world, m).
        distance: ``(k,)`` float32 distance to it (m), capped at the search radius.
        lost: ``(k,)`` bool, no fresh data for the agent this time (its worker failed or its scene
            is being placed on another worker): the row holds its last good data (zeros and
            ``far`` depth if none) and the env truncates the agent.
        timings: seconds per stage (see :meth:`Aggregator.collect`).
    """

    images: dict[str, np.ndarray]
    collision: np.ndarray
    inside: np.ndarray
    nearest: np.ndarray
    distance: np.ndarray
    lost: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)

    def take(self, rows: np.ndarray) -> "Observation":
        """The rows ``rows`` (a copy), with the same timings."""
        return Observation({k: v[rows] for k, v in self.images.items()}, self.collision[rows], self.inside[rows],
                           self.nearest[rows], self.distance[rows], self.lost[rows], dict(self.timings))


def blank_observation(cameras: Sequence[CameraSpec], n: int, search_radius: float) -> Observation:
    """``n`` rows of "nothing seen": far depth, zero images, no obstacle within reach."""
    images = {c.name: np.full((n, *c.shape), c.far if c.kind == "depth" else 0, dtype=c.dtype) for c in cameras}
    return Observation(images, np.zeros(n, bool), np.zeros(n, bool), np.zeros((n, 3), np.float32),
                       np.full(n, search_radius, np.float32), np.ones(n, bool))


def empty_observation(cameras: Sequence[CameraSpec], n: int, images: dict[str, np.ndarray] | None = None) -> Observation:
    """Uninitialised buffers for ``n`` rows (every row is written before it is read): ``images`` if
    given (a step segment's; no image array is allocated then), else fresh image arrays."""
    if images is None:
        images = {c.name: np.empty((n, *c.shape), dtype=c.dtype) for c in cameras}
    return Observation(images, np.empty(n, bool), np.empty(n, bool), np.empty((n, 3), np.float32),
                       np.empty(n, np.float32), np.ones(n, bool))


def scatter_reply(obs: Observation, obs_rows: np.ndarray, spawn: Observation, spawn_rows: np.ndarray,
                  reply: dict[str, Any], cameras: Sequence[CameraSpec], worker_id: str,
                  images_in_place: bool = False) -> None:
    """Write a ``step_result`` whose first ``len(obs_rows)`` rows belong to ``obs``' rows ``obs_rows``
    and the others to ``spawn``'s rows ``spawn_rows``; checks every shape first (one pass for both).

    ``images_in_place``: the worker wrote the images straight into ``obs``' and ``spawn``'s (a step segment).
    """
    n_obs = len(obs_rows)
    n = n_obs + len(spawn_rows)
    images = reply.get("images") or {}
    expected: list[tuple[str, Any, tuple[int, ...]]] = (
        [] if images_in_place else [(cam.name, images.get(cam.name), (n, *cam.shape)) for cam in cameras])
    expected += [("collision", reply.get("collision"), (n,)), ("inside", reply.get("inside"), (n,)),
                 ("nearest", reply.get("nearest"), (n, 3)), ("distance", reply.get("distance"), (n,))]
    for name, value, shape in expected:
        if not isinstance(value, np.ndarray) or value.shape != shape:
            got = getattr(value, "shape", type(value).__name__)
            raise ProtocolError(f"worker {worker_id!r} sent {name} of shape {got}; expected {shape}")
    parts = ((obs, obs_rows, slice(0, n_obs)), (spawn, spawn_rows, slice(n_obs, n))) if n > n_obs else \
        ((obs, obs_rows, slice(None)),)
    for out, rows, part in parts:
        if not images_in_place:
            for cam in cameras:
                out.images[cam.name][rows] = images[cam.name][part]
        for key in QUERY_FIELDS:
            getattr(out, key)[rows] = reply[key][part]
        out.lost[rows] = False


def copy_rows(out: Observation, rows: np.ndarray, source: Observation, source_rows: np.ndarray) -> None:
    """Fill ``out``'s rows ``rows`` from ``source`` (last good data); they stay marked lost."""
    for name, image in out.images.items():
        image[rows] = source.images[name][source_rows]
    for key in QUERY_FIELDS:
        getattr(out, key)[rows] = getattr(source, key)[source_rows]
    out.lost[rows] = True


PENDING_LIMIT = 2
"""Partial observations :class:`LastGood` keeps as they are before copying the oldest in: two
groups stepped in turn each replace their own, so neither is ever copied."""


class LastGood:
    """Each agent's last good data: what a lost agent is given (blank until it was served once).

    A full observation is kept as it is (no copy). So are the last :data:`PENDING_LIMIT` partial
    ones (each step of a group replaces the group's previous one, whose rows it all covers): they
    are written into a private copy, in the order they came, only when a lost agent needs it or
    when more come; never into arrays already handed out to a caller. Observations handed out are
    read only, to the aggregator and its callers alike, so keeping them is keeping their data; the
    one writer is the env of a step taken with ``terminal="ended"``, which writes the first views of
    the agents it resets into their rows before it hands the step out: those rows then hold each
    such agent's newest view, which is what it should get if its worker is lost next.
    """

    def __init__(self, cameras: Sequence[CameraSpec], num_agents: int, search_radius: float) -> None:
        self.num_agents = num_agents
        self._every = np.arange(num_agents)
        self.obs = blank_observation(cameras, num_agents, search_radius)
        self._private = True  # False while obs is an observation handed out by collect()
        self._pending: list[tuple[Observation, np.ndarray, np.ndarray]] = []  # (obs, rows, agents), oldest first

    def fill(self, out: Observation, rows: np.ndarray, agents: np.ndarray) -> None:
        """Write ``agents``' last good data into ``out``'s ``rows`` (marked lost)."""
        self._flush(len(self._pending))
        copy_rows(out, rows, self.obs, agents)

    def remember(self, obs: Observation, rows: np.ndarray, agents: np.ndarray) -> None:
        """Keep ``obs``' fresh ``rows`` as the last good data of ``agents``."""
        if len(agents) == self.num_agents and (agents == self._every).all():
            self.obs, self._private, self._pending = obs, False, []
            return
        if not len(rows):
            return
        covered = np.zeros(self.num_agents, dtype=bool)
        covered[agents] = True
        # an earlier one whose agents this one all covers would only be written over
        self._pending = [p for p in self._pending if not covered[p[2]].all()]
        self._pending.append((obs, rows, agents))
        self._flush(len(self._pending) - PENDING_LIMIT)

    def _flush(self, count: int) -> None:
        """Write the oldest ``count`` pending observations into the private copy, in order."""
        if count <= 0:
            return
        if not self._private:
            self.obs, self._private = self.obs.take(np.arange(self.num_agents)), True
        last = self.obs
        for obs, rows, agents in self._pending[:count]:
            for name, image in last.images.items():
                image[agents] = obs.images[name][rows]
            for key in QUERY_FIELDS:
                getattr(last, key)[agents] = getattr(obs, key)[rows]
        del self._pending[:count]
