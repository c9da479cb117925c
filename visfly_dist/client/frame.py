"""What the workers saw, as torch tensors: images (with sensor noise) and obstacle queries.

The aggregator deals in numpy; this module is where its ``Observation`` crosses into torch, noise
is applied (batched, seeded) and the fresh rows of reset agents are merged in (into reused
buffers, see :mod:`visfly_dist.client.buffer_pool`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np
import torch

from visfly_dist.client.buffer_pool import BufferPool
from visfly_dist.client.noise import SensorNoise


@dataclass
class SensorFrame:
    """Per-agent sensor readings of one step.

    Attributes:
        images: camera name -> ``(N, C, H, W)``: depth float32 metres, RGB uint8, segmentation int32.
        collision: ``(N,)`` bool, the drone's sphere touches an obstacle.
        inside: ``(N,)`` bool, the drone is inside a closed obstacle.
        nearest: ``(N, 3)`` world point of the nearest obstacle, metres.
        distance: ``(N,)`` distance to that point (capped at the search radius), metres.
        lost: ``(N,)`` bool, no worker answered for this agent (its readings are placeholders).
    """

    images: dict[str, torch.Tensor]
    collision: torch.Tensor
    inside: torch.Tensor
    nearest: torch.Tensor
    distance: torch.Tensor
    lost: torch.Tensor

    @classmethod
    def from_observation(cls, obs: Any, device: torch.device, noise: Mapping[str, SensorNoise],
                         generator: torch.Generator, cameras: Sequence[str]) -> "SensorFrame":
        """Convert an aggregator ``Observation`` (numpy) and apply each camera's noise.

        Only the images of ``cameras`` are kept (in that order).
        """
        images = {}
        for name in cameras:
            image = _image_tensor(np.asarray(obs.images[name]), device)
            model = noise.get(name)
            images[name] = model(image, generator) if model else image
        return cls(
            images=images,
            collision=_tensor(np.asarray(obs.collision, dtype=bool), device),
            inside=_tensor(np.asarray(obs.inside, dtype=bool), device),
            nearest=_tensor(np.asarray(obs.nearest, dtype=np.float32), device),
            distance=_tensor(np.asarray(obs.distance, dtype=np.float32), device),
            lost=_tensor(np.asarray(obs.lost, dtype=bool), device),
        )

    def scatter(self, index: torch.Tensor, rows: "SensorFrame", buffers: BufferPool | None = None,
                in_place: bool = False) -> "SensorFrame":
        """A frame whose rows ``index`` come from ``rows`` (which holds exactly those rows).

        This frame is left as it is, unless ``in_place``: then its images are written into (the
        caller owns them: nothing else refers to them) and the new frame shares them; the small
        per-agent tensors are copied either way. With ``buffers`` the merged CPU images are written
        into a buffer of that pool (its pages already mapped) instead of a fresh tensor.
        """

        span = row_span(index)  # a group's consecutive rows: images copied as one block (~3x index_copy_)

        def put(full: torch.Tensor, part: torch.Tensor) -> torch.Tensor:
            return full.index_copy(0, index, part)  # index_copy: images ~8x faster than out[index] =

        def put_rows(out: torch.Tensor, part: torch.Tensor) -> torch.Tensor:
            if span is None:
                return out.index_copy_(0, index, part)
            out[span].copy_(part)
            return out

        def put_image(full: torch.Tensor, part: torch.Tensor) -> torch.Tensor:
            if in_place:
                return put_rows(full, part)
            if buffers is None or full.device.type != "cpu":
                return put(full, part)
            return put_rows(buffers.take(tuple(full.shape), full.dtype).copy_(full), part)

        return SensorFrame(
            images={k: put_image(v, rows.images[k]) for k, v in self.images.items()},
            collision=put(self.collision, rows.collision),
            inside=put(self.inside, rows.inside),
            nearest=put(self.nearest, rows.nearest),
            distance=put(self.distance, rows.distance),
            lost=put(self.lost, rows.lost),
        )


def row_span(ids: torch.Tensor) -> slice | None:
    """Row indices ``ids`` as a slice where they are consecutive and ascending (a group of the
    trainer's), else ``None``."""
    if not len(ids):
        return None
    first, last = int(ids[0]), int(ids[-1])
    if last - first + 1 != len(ids) or (len(ids) > 2 and not bool((ids.diff() == 1).all())):
        return None
    return slice(first, last + 1)


def _image_tensor(array: np.ndarray, device: torch.device) -> torch.Tensor:
    if array.dtype == np.uint16:  # torch's uint16 supports few ops; ids fit in int32
        array = array.astype(np.int32)
    return _tensor(np.ascontiguousarray(array), device)


def _tensor(array: np.ndarray, device: torch.device) -> torch.Tensor:
    """``array`` as a tensor on ``device``: on the CPU a view (``from_numpy``: a third of ``as_tensor``'s cost)."""
    return torch.from_numpy(array) if device.type == "cpu" else torch.as_tensor(array, device=device)
