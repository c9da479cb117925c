"""A worker's bounds: what one request and the whole worker may ask for (light to import)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

from visfly_dist.errors import ConfigError

MIB = 1024 * 1024
MEMORY_SHARE = 0.5
"""Share of the host's physical memory one worker may fill with scenes by default."""
LOAD_RESERVE_BYTES = 128 * MIB
"""Memory set aside per load running when a worker decides whether another load may start beside
it: more than one maximum-density garage adds (about 89 MB; a default garage about 9 MB)."""


def host_memory_bytes() -> int | None:
    """Physical memory of this host, bytes (``None`` where it cannot be read)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def default_max_memory_bytes() -> int:
    """Half the host's physical memory (8 GiB where it cannot be read)."""
    total = host_memory_bytes()
    return int(total * MEMORY_SHARE) if total else 8 * 1024 * MIB


def resident_bytes() -> int | None:
    """This process's resident memory, bytes (``None`` where ``/proc/self/statm`` is missing)."""
    try:
        with open("/proc/self/statm", "rb") as f:
            return int(f.read().split()[1]) * int(os.sysconf("SC_PAGE_SIZE"))
    except (OSError, ValueError, IndexError):
        return None


@dataclass(frozen=True)
class WorkerLimits:
    """What one worker accepts; beyond it a request gets an error reply, never an exhausted worker.

    Attributes:
        max_scenes: scenes loaded or loading at once (``overloaded`` beyond).
        max_key_chars: length of a scene key a load may create (``too_large`` beyond).
        max_pixels: agents x cameras x pixels one step may render (``too_large`` beyond).
        max_memory_bytes: resident memory of the worker process; a load is refused (``overloaded``)
            when the worker is at it when the load is accepted or starts, or past it once the scene
            is built (the scene is dropped then). A load starts beside others only while
            :data:`LOAD_RESERVE_BYTES` per load running fit under it. One maximum-density garage
            adds about 89 MB. Default: half the host's physical memory.
    """

    max_scenes: int = 1024
    max_key_chars: int = 64
    max_pixels: int = 64 * 1024 * 1024
    max_memory_bytes: int = field(default_factory=default_max_memory_bytes)

    def __post_init__(self) -> None:
        problems = [f"{name}={getattr(self, name)!r} must be an int in [{lo}, {hi}]"
                    for name, lo, hi in (("max_scenes", 1, 100_000), ("max_key_chars", 1, 256), ("max_pixels", 1, 2**40),
                                         ("max_memory_bytes", MIB, 2**50))
                    if isinstance(getattr(self, name), bool) or not isinstance(getattr(self, name), int)
                    or not lo <= getattr(self, name) <= hi]
        if problems:
            raise ConfigError("invalid WorkerLimits: " + "; ".join(problems))

    def to_dict(self) -> dict[str, int]:
        return {"max_scenes": self.max_scenes, "max_key_chars": self.max_key_chars, "max_pixels": self.max_pixels,
                "max_memory_bytes": self.max_memory_bytes}
