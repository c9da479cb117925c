"""Camera (sensor) specification shared by the client, the aggregator and the workers.

Conventions (docs/ARCHITECTURE.md): the camera looks along body +x by default, z up in the image's "up";
pinhole with square pixels and a horizontal field of view. Depth is metric distance along the
optical axis, float32 ``(1, H, W)``; no hit gives ``far``. RGB is uint8 ``(3, H, W)``.
Segmentation is uint16 object ids ``(1, H, W)``, 0 = nothing.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Mapping

import numpy as np

from visfly_dist.errors import ConfigError

SENSOR_KINDS = ("depth", "rgb", "segmentation")
MAX_RESOLUTION = 2048


@dataclass(frozen=True)
class CameraSpec:
    """One camera mounted on every drone.

    Attributes:
        name: observation key, unique per env (e.g. ``"depth"``).
        kind: ``"depth"``, ``"rgb"`` or ``"segmentation"``.
        width: image width in pixels.
        height: image height in pixels.
        hfov_deg: horizontal field of view in degrees.
        offset: mount position in the body frame (FLU), metres.
        rotation: mount rotation body->camera as a unit quaternion ``wxyz``; identity looks along
            body +x. A downward camera is a +90 deg pitch: ``(cos(pi/4), 0, sin(pi/4), 0)``.
        near: near clip plane, metres.
        far: depth for rays that hit nothing (and far clip plane), metres.
    """

    name: str = "depth"
    kind: str = "depth"
    width: int = 64
    height: int = 64
    hfov_deg: float = 90.0
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    near: float = 0.05
    far: float = 20.0

    def __post_init__(self) -> None:
        problems = self.problems()
        if problems:
            raise ConfigError(f"invalid CameraSpec {self.name!r}: " + "; ".join(problems))
        norm = math.sqrt(sum(c * c for c in self.rotation))
        object.__setattr__(self, "rotation", tuple(float(c) / norm for c in self.rotation))
        object.__setattr__(self, "offset", tuple(float(c) for c in self.offset))

    def problems(self) -> list[str]:
        """Every problem with this spec, as messages (empty when valid). Types are strict: a bool is
        not a number, a string is not a vector."""
        out: list[str] = []
        if not isinstance(self.name, str) or not self.name or "/" in self.name:
            out.append(f"name={self.name!r} must be a non-empty string without '/'")
        if not isinstance(self.kind, str) or self.kind not in SENSOR_KINDS:
            out.append(f"kind={self.kind!r} must be one of {SENSOR_KINDS}")
        for attr in ("width", "height"):
            v = getattr(self, attr)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 1 <= int(v) <= MAX_RESOLUTION:
                out.append(f"{attr}={v!r} must be an int in [1, {MAX_RESOLUTION}]")
        if not (_is_number(self.hfov_deg) and 1.0 <= float(self.hfov_deg) <= 170.0):
            out.append(f"hfov_deg={self.hfov_deg!r} must be a number in [1, 170]")
        if not _is_vector(self.offset, 3):
            out.append(f"offset={self.offset!r} must be 3 finite numbers")
        if not _is_vector(self.rotation, 4) or sum(float(c) ** 2 for c in self.rotation) < 1e-12:
            out.append(f"rotation={self.rotation!r} must be a non-zero quaternion wxyz (4 finite numbers)")
        if not (_is_number(self.near) and _is_number(self.far) and 0 < float(self.near) < float(self.far) <= 1e4):
            out.append(f"near={self.near!r}, far={self.far!r} must be numbers with 0 < near < far <= 1e4")
        return out

    @property
    def channels(self) -> int:
        return 3 if self.kind == "rgb" else 1

    @property
    def shape(self) -> tuple[int, int, int]:
        """Image shape ``(C, H, W)``."""
        return (self.channels, self.height, self.width)

    @property
    def dtype(self) -> np.dtype:
        return np.dtype({"depth": np.float32, "rgb": np.uint8, "segmentation": np.uint16}[self.kind])

    @property
    def focal_px(self) -> float:
        """Focal length in pixels (square pixels)."""
        return 0.5 * self.width / math.tan(math.radians(self.hfov_deg) / 2.0)

    @property
    def vfov_deg(self) -> float:
        return math.degrees(2.0 * math.atan(0.5 * self.height / self.focal_px))

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["offset"] = list(self.offset)
        d["rotation"] = list(self.rotation)
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "CameraSpec":
        """Build from a decoded message; unknown or missing keys raise ConfigError."""
        if not isinstance(d, Mapping):
            raise ConfigError(f"camera spec must be a map, got {type(d).__name__}")
        allowed = set(cls.__dataclass_fields__)
        unknown = set(d) - allowed
        if unknown:
            raise ConfigError(f"camera spec has unknown keys {sorted(unknown)}; accepted: {sorted(allowed)}")
        kw = dict(d)
        for key in ("offset", "rotation"):
            if isinstance(kw.get(key), list):
                kw[key] = tuple(kw[key])
        try:
            return cls(**kw)
        except TypeError as exc:
            raise ConfigError(f"camera spec {d!r}: {exc}") from exc


def _is_number(value: Any) -> bool:
    """A finite real number that is not a bool."""
    return (isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
            and math.isfinite(float(value)))


def _is_vector(value: Any, length: int) -> bool:
    """A tuple, list or 1-d array of ``length`` finite numbers."""
    if isinstance(value, np.ndarray):
        value = value.tolist() if value.ndim == 1 else None
    return isinstance(value, (tuple, list)) and len(value) == length and all(_is_number(v) for v in value)


DEFAULT_DEPTH_CAMERA = CameraSpec()
