"""Airframes: the physical parameters of a quadrotor and its controller gains, loaded from JSON.

The shipped airframes live in ``visfly_dist/dynamics/airframes/*.json`` (``visfly``, ``visfly-fast``,
``visfly-large``); ``load_airframe`` also takes a path to a JSON file of the same shape.

Every number may be a Python float or a torch tensor. Tensors that require grad stay in the graph
when a ``Quadrotor`` is built from the airframe, so gradients with respect to mass, inertia, drag
and so on come for free: ``Quadrotor(cfg, dataclasses.replace(af, mass=m), ...)`` with
``m.requires_grad_()``. Build the ``Quadrotor`` inside the differentiated computation (it is cheap),
because its constants are derived from the airframe once, at construction.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, fields
from pathlib import Path
from typing import AbstractSet, Any, Sequence, Union

import torch

from visfly_dist.errors import ConfigError

AIRFRAME_DIR = Path(__file__).resolve().parent / "airframes"

Number = Union[float, torch.Tensor]
Vector3 = Union[Sequence[float], torch.Tensor]


@dataclass(frozen=True)
class ControllerGains:
    """Gains of the built-in controllers, in acceleration units (independent of mass and inertia).

    Attributes:
        rate_p: body-rate P gain per axis, 1/s (CTBR).
        rate_d: body-rate D gain, dimensionless: the rate error's derivative is the measured angular
            acceleration (CTBR).
        attitude_p: SO(3) attitude gain per axis, 1/s^2 (LV, PS; Lee et al.).
        attitude_d: SO(3) angular-velocity gain per axis, 1/s (LV, PS).
        velocity_p: velocity P gain per world axis, 1/s (LV, PS).
        position_p: position P gain per world axis, 1/s (PS: gives the velocity set point).
        max_horizontal_accel: bound on the commanded horizontal acceleration, m/s^2 (tilt limit).
        vertical_accel_range: bounds on the commanded vertical acceleration, m/s^2.
    """

    rate_p: Vector3
    rate_d: Number
    attitude_p: Vector3
    attitude_d: Vector3
    velocity_p: Vector3
    position_p: Vector3
    max_horizontal_accel: Number
    vertical_accel_range: Sequence[float]


@dataclass(frozen=True)
class Airframe:
    """Physical parameters of one quadrotor (X layout, body frame FLU, rotors numbered as PX4).

    Rotor ``i`` sits at ``arm_length / sqrt(2) * (sx_i, sy_i)`` with ``sx = (+1, -1, +1, -1)``,
    ``sy = (-1, +1, +1, -1)`` (front-right, back-left, front-left, back-right); rotors 0 and 1 spin
    counter-clockwise seen from above (yaw torque ``-kappa * T``), rotors 2 and 3 clockwise
    (``+kappa * T``).

    Attributes:
        name: airframe name.
        mass: kg.
        inertia: diagonal of the inertia matrix, kg m^2.
        arm_length: centre-to-rotor distance, m.
        yaw_torque_coeff: kappa, yaw torque per newton of rotor thrust, m.
        thrust_coeffs: ``(a, b, c)`` of the rotor thrust ``T = a w^2 + b w + c``, N with w in rad/s.
        rotor_speed_range: ``(min, max)`` rotor speed, rad/s.
        motor_time_constant: first-order lag of rotor speed, s.
        drag_linear: body-frame linear drag per axis, N/(m/s).
        drag_area: body-frame drag coefficient times area per axis (Cd A), m^2.
        air_density: kg/m^3; the quadratic drag coefficient is ``0.5 * air_density * drag_area``.
        max_body_rate: CTBR body-rate range, rad/s.
        max_collective_accel: CTBR collective (mass-normalised) thrust range, m/s^2.
        gains: controller gains.
        description: one line about where the numbers come from.
    """

    name: str
    mass: Number
    inertia: Vector3
    arm_length: Number
    yaw_torque_coeff: Number
    thrust_coeffs: Sequence[Number]
    rotor_speed_range: Sequence[float]
    motor_time_constant: Number
    drag_linear: Vector3
    drag_area: Vector3
    air_density: Number
    max_body_rate: float
    max_collective_accel: float
    gains: ControllerGains
    description: str = ""

    def __post_init__(self) -> None:
        problems = self.problems()
        if problems:
            raise ConfigError(f"invalid airframe {self.name!r}: " + "; ".join(problems))

    def problems(self) -> list[str]:
        """Every problem with these parameters, as messages (empty when valid)."""
        out: list[str] = []

        def positive(name: str, value: Any) -> None:
            v = torch.as_tensor(value, dtype=torch.float64).detach()
            if v.numel() == 0 or not bool(torch.all(v > 0)):
                out.append(f"{name}={_show(value)} must be > 0")

        def length(name: str, value: Any, n: int) -> None:
            if torch.as_tensor(value).numel() != n:
                out.append(f"{name}={_show(value)} must have {n} entries")

        for name in ("mass", "arm_length", "motor_time_constant", "max_body_rate",
                     "max_collective_accel", "inertia"):
            positive(name, getattr(self, name))
        length("inertia", self.inertia, 3)
        length("drag_linear", self.drag_linear, 3)
        length("drag_area", self.drag_area, 3)
        length("thrust_coeffs", self.thrust_coeffs, 3)
        lo, hi = (_float(x) for x in self.rotor_speed_range)
        if not 0 <= lo < hi:
            out.append(f"rotor_speed_range={_show(self.rotor_speed_range)} must be 0 <= min < max")
        elif len(out) == 0:
            a, b, _ = (_float(x) for x in self.thrust_coeffs)
            if a < 0 or 2 * a * lo + b <= 0:
                out.append(f"thrust_coeffs={_show(self.thrust_coeffs)} must give thrust increasing "
                           f"with rotor speed over {_show(self.rotor_speed_range)}")
            elif 4 * self.thrust(hi) <= 9.81 * _float(self.mass):
                out.append(f"max thrust 4*T({hi})={4 * self.thrust(hi):.3f} N cannot lift "
                           f"mass={_float(self.mass)} kg")
        return out

    def thrust(self, rotor_speed: float) -> float:
        """Thrust of one rotor at ``rotor_speed`` rad/s, in newtons (plain float)."""
        a, b, c = (_float(x) for x in self.thrust_coeffs)
        return a * rotor_speed**2 + b * rotor_speed + c

    @property
    def max_rotor_thrust(self) -> float:
        """Thrust of one rotor at its top speed, N."""
        return self.thrust(_float(self.rotor_speed_range[1]))


def _float(value: Number) -> float:
    """A plain float of a number or one-element tensor (outside any autograd graph)."""
    return float(value.detach()) if isinstance(value, torch.Tensor) else float(value)


def _show(value: Any) -> str:
    if isinstance(value, torch.Tensor):
        return str(value.detach().tolist())
    return repr(value)


def list_airframes() -> list[str]:
    """Names of the shipped airframes."""
    return sorted(p.stem for p in AIRFRAME_DIR.glob("*.json"))


def load_airframe(name_or_path: str | Path) -> Airframe:
    """Load a shipped airframe by name (``"visfly"``) or any airframe JSON file by path.

    Raises:
        ConfigError: unknown name, unreadable file, or missing/unknown/invalid fields.
    """
    path = Path(name_or_path)
    if path.suffix != ".json":
        path = AIRFRAME_DIR / f"{name_or_path}.json"
        if not path.is_file():
            raise ConfigError(f"unknown airframe {str(name_or_path)!r}: shipped airframes are "
                              f"{list_airframes()}; or pass the path of an airframe .json file")
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ConfigError(f"cannot read airframe file {str(path)!r}: {exc}") from exc
    return airframe_from_dict(data, source=str(path))


def airframe_from_dict(data: dict[str, Any], source: str = "<dict>") -> Airframe:
    """Build an ``Airframe`` from its JSON form (see the shipped files for the layout)."""
    data = dict(data)
    if "radius" in data:
        raise ConfigError(f"airframe {source!r}: 'radius' is not an airframe field; the collision radius is "
                          f"the env setting drone_radius (EnvConfig, default 0.1 m): remove it from the file "
                          f"and pass drone_radius={data['radius']!r} to the env instead")
    gains = data.pop("gains", None)
    if not isinstance(gains, dict):
        raise ConfigError(f"airframe {source!r} needs a 'gains' object with {_names(ControllerGains)}")
    _check_keys(data, Airframe, source, optional={"description", "gains"})
    _check_keys(gains, ControllerGains, f"{source} gains")
    return Airframe(**data, gains=ControllerGains(**gains))


def _names(cls: type) -> list[str]:
    return [f.name for f in fields(cls)]


def _check_keys(data: dict[str, Any], cls: type, source: str, optional: AbstractSet[str] = frozenset()) -> None:
    expected = set(_names(cls))
    missing = expected - set(data) - set(optional)
    unknown = set(data) - expected
    if missing or unknown:
        raise ConfigError(f"airframe {source!r}: missing fields {sorted(missing)}, unknown fields "
                          f"{sorted(unknown)}; expected {sorted(expected)}")
