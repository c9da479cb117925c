"""Sensor noise models: batched torch, driven by an explicit ``torch.Generator``.

Each sensor (a camera by name, or ``"state"``) takes a list of :class:`NoiseSpec` applied in order.
The kinds follow Table II of the VisFly paper:

| kind          | sensors                 | model (x: clean value)                                        | params (default)                          |
|---------------|-------------------------|---------------------------------------------------------------|-------------------------------------------|
| ``gaussian``  | all                     | ``x + N(mean, std)``                                          | ``mean`` (0), ``std`` (required)          |
| ``uniform``   | state                   | ``x + U(-half_width, half_width)``                            | ``half_width`` (required)                 |
| ``poisson``   | rgb, depth, segmentation| shot noise ``Poisson(x * scale) / scale`` (mean x, var x/scale)| ``scale`` (1.0) counts per unit value     |
| ``salt_pepper``| rgb, depth, segmentation| each element with prob. ``amount`` becomes high (salt, prob. ``salt_ratio``) or low (pepper) | ``amount`` (required), ``salt_ratio`` (0.5) |
| ``speckle``   | rgb, depth, segmentation| multiplicative ``x + x * N(0, std)``                          | ``std`` (required)                        |
| ``redwood``   | depth                   | simplified Redwood depth-camera model, see below              | ``k`` (0.002), ``baseline_focal`` (35.0), ``subpixel`` (8.0), ``dropout`` (0.0) |

``redwood`` (after the Redwood/Kinect noise model, simplified): ``d1 = d + N(0, k * d^2)`` (noise
grows with the square of distance, ``k`` in 1/m); then quantised in disparity space
``disp = baseline_focal / d1`` (metres x pixels) rounded to ``1/subpixel`` pixel, ``d2 =
baseline_focal / disp``; finally each pixel drops out to ``far`` (no return) with probability
``dropout * d / far`` (far pixels drop out more often). Pixels at ``far`` or ``<= 0`` (no reading) stay as they are.

Images are clamped to their sensor range after noise: RGB ``[0, 255]`` and rounded, depth
``[0, far]``, segmentation ``[0, 65535]`` and rounded. Salt and pepper use the ends of that range
(depth: pepper 0 = invalid reading, salt ``far`` = no return).
"""  # noqa: E501

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import torch

from visfly_dist.errors import ConfigError

SENSOR_RANGES = {"rgb": (0.0, 255.0), "segmentation": (0.0, 65535.0)}
"""Value range of each integer image kind; depth's range is ``[0, far]`` of its camera."""

# kind -> (sensors it applies to, {param: default or None when required}, {param: (lo, hi)})
_IMAGE = ("rgb", "depth", "segmentation")
NOISE_KINDS: dict[str, tuple[tuple[str, ...], dict[str, float | None], dict[str, tuple[float, float]]]] = {
    "gaussian": (("state", *_IMAGE), {"mean": 0.0, "std": None}, {"mean": (-1e6, 1e6), "std": (0.0, 1e6)}),
    "uniform": (("state",), {"half_width": None}, {"half_width": (0.0, 1e6)}),
    "poisson": (_IMAGE, {"scale": 1.0}, {"scale": (1e-6, 1e6)}),
    "salt_pepper": (_IMAGE, {"amount": None, "salt_ratio": 0.5}, {"amount": (0.0, 1.0), "salt_ratio": (0.0, 1.0)}),
    "speckle": (_IMAGE, {"std": None}, {"std": (0.0, 1e3)}),
    "redwood": (("depth",), {"k": 0.002, "baseline_focal": 35.0, "subpixel": 8.0, "dropout": 0.0},
                {"k": (0.0, 10.0), "baseline_focal": (1e-3, 1e6), "subpixel": (1e-3, 1e3), "dropout": (0.0, 1.0)}),
}


@dataclass(frozen=True)
class NoiseSpec:
    """One noise model of one sensor.

    Attributes:
        kind: one of :data:`NOISE_KINDS` (``gaussian``, ``uniform``, ``poisson``, ``salt_pepper``,
            ``speckle``, ``redwood``).
        params: the model's parameters (see the module docstring); missing optional ones take
            their defaults.
    """

    kind: str
    params: Mapping[str, float] = field(default_factory=dict)

    def problems(self, sensor: str) -> list[str]:
        """Every problem with this spec for a sensor kind (``state``, ``rgb``, ``depth``, ``segmentation``)."""
        if self.kind not in NOISE_KINDS:
            return [f"noise kind={self.kind!r} is unknown; valid kinds: {', '.join(NOISE_KINDS)}"]
        sensors, defaults, ranges = NOISE_KINDS[self.kind]
        out = []
        if sensor not in sensors:
            out.append(f"noise kind={self.kind!r} does not apply to a {sensor} sensor; it applies to {sensors}")
        if not isinstance(self.params, Mapping):
            return out + [f"noise {self.kind!r} params must be a mapping, got {type(self.params).__name__}"]
        unknown = sorted(set(self.params) - set(defaults))
        if unknown:
            out.append(f"noise {self.kind!r} has unknown params {unknown}; accepted: {sorted(defaults)}")
        for name, default in defaults.items():
            if name not in self.params:
                if default is None:
                    out.append(f"noise {self.kind!r} needs param {name!r}")
                continue
            value = self.params[name]
            lo, hi = ranges[name]
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or not lo <= value <= hi:
                out.append(f"noise {self.kind!r} param {name}={value!r} must be a finite number in [{lo}, {hi}]")
        return out

    def resolved(self) -> dict[str, float]:
        """The parameters with defaults filled in (call on a valid spec)."""
        defaults = NOISE_KINDS[self.kind][1]
        return {k: float(self.params.get(k, d)) for k, d in defaults.items()}  # type: ignore[arg-type]


def apply_noise(x: torch.Tensor, spec: NoiseSpec, generator: torch.Generator, high: float = 20.0) -> torch.Tensor:
    """One noise model on a float tensor (no clamping; see :class:`SensorNoise`).

    ``high`` is the top of the sensor's range: the salt value, and ``far`` for ``redwood``.
    """
    p = spec.resolved()
    if spec.kind == "gaussian":
        return x + p["mean"] + p["std"] * _randn(x, generator)
    if spec.kind == "uniform":
        return x + p["half_width"] * (2.0 * _rand(x, generator) - 1.0)
    if spec.kind == "speckle":
        return x + x * p["std"] * _randn(x, generator)
    if spec.kind == "poisson":
        scale = p["scale"]
        return torch.poisson(x.clamp(min=0.0) * scale, generator=generator) / scale
    if spec.kind == "salt_pepper":
        u = _rand(x, generator)
        salt = u < p["amount"] * p["salt_ratio"]
        pepper = (u >= p["amount"] * p["salt_ratio"]) & (u < p["amount"])
        return torch.where(salt, torch.full_like(x, high), torch.where(pepper, torch.zeros_like(x), x))
    assert spec.kind == "redwood", spec.kind
    return _redwood(x, p, generator, high)


def _redwood(d: torch.Tensor, p: dict[str, float], generator: torch.Generator, far: float) -> torch.Tensor:
    valid = (d > 0) & (d < far)
    d1 = d + p["k"] * d * d * _randn(d, generator)
    d1 = d1.clamp(min=1e-3)
    disp = p["baseline_focal"] / d1
    disp = torch.round(disp * p["subpixel"]).clamp(min=1.0) / p["subpixel"]
    d2 = p["baseline_focal"] / disp
    drop = _rand(d, generator) < p["dropout"] * (d / far).clamp(0.0, 1.0)
    return torch.where(valid, torch.where(drop, torch.full_like(d, far), d2), d)


def _randn(x: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    return torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype)


def _rand(x: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    return torch.rand(x.shape, generator=generator, device=x.device, dtype=x.dtype)


class SensorNoise:
    """The noise chain of one sensor, with its clamping and output dtype.

    Args:
        specs: models applied in order.
        sensor: ``"state"``, ``"rgb"``, ``"depth"`` or ``"segmentation"``.
        far: the camera's ``far`` (depth range and salt value); ignored otherwise.
    """

    def __init__(self, specs: Sequence[NoiseSpec], sensor: str, far: float = 20.0) -> None:
        problems = [p for s in specs for p in s.problems(sensor)]
        if problems:
            raise ConfigError(f"invalid noise for a {sensor} sensor: " + "; ".join(problems))
        self.specs = tuple(specs)
        self.sensor = sensor
        self.far = float(far)

    def __bool__(self) -> bool:
        return bool(self.specs)

    def __call__(self, x: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """Noisy copy of ``x`` (any shape); integer images come back rounded, in their dtype."""
        if not self.specs:
            return x
        dtype = x.dtype
        y = x.float() if not x.is_floating_point() else x
        lo, hi = SENSOR_RANGES.get(self.sensor, (0.0, self.far))
        for spec in self.specs:
            y = apply_noise(y, spec, generator, high=hi)
        if self.sensor == "state":
            return y
        y = y.clamp(lo, hi)
        if not dtype.is_floating_point:
            y = torch.round(y).to(dtype)
        return y
