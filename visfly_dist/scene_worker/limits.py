"""A worker's bounds: what one request and the whole worker may ask for (light to import)."""

from __future__ import annotations

from dataclasses import dataclass

from visfly_dist.errors import ConfigError


@dataclass(frozen=True)
class WorkerLimits:
    """What one worker accepts; beyond it a request gets an error reply, never an exhausted worker.

    Attributes:
        max_scenes: scenes loaded or loading at once (``overloaded`` beyond).
        max_key_chars: length of a scene key a load may create (``too_large`` beyond).
        max_pixels: agents x cameras x pixels one step may render (``too_large`` beyond).
    """

    max_scenes: int = 1024
    max_key_chars: int = 64
    max_pixels: int = 64 * 1024 * 1024

    def __post_init__(self) -> None:
        problems = [f"{name}={getattr(self, name)!r} must be an int in [1, {hi}]"
                    for name, hi in (("max_scenes", 100_000), ("max_key_chars", 256), ("max_pixels", 2**40))
                    if isinstance(getattr(self, name), bool) or not isinstance(getattr(self, name), int)
                    or not 1 <= getattr(self, name) <= hi]
        if problems:
            raise ConfigError("invalid WorkerLimits: " + "; ".join(problems))

    def to_dict(self) -> dict[str, int]:
        return {"max_scenes": self.max_scenes, "max_key_chars": self.max_key_chars, "max_pixels": self.max_pixels}
