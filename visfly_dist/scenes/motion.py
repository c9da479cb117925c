"""Paths of moving obstacles: a circle, a closed polygon, a periodic cubic spline (pure numpy).

Every path is closed and travelled at a constant ``speed`` (m/s) by arc length, so an obstacle's
position at time ``t`` is the point at arc length ``(speed * t) mod length`` from the path's start,
and it comes back to it every ``period = length / speed`` seconds. :meth:`Motion.state` evaluates
position, velocity and acceleration for an array of times at once; it is a pure function of ``t``
(no state), so a worker and a client computing it from the same dict get the same answer.

- ``circle``: ``centre``, ``radius``, ``speed``, ``axis`` (the circle's normal, default +z; the
  obstacle turns counter-clockwise about it) and ``phase`` (the start angle, rad, from the first
  in-plane axis: +x for the default axis). Acceleration is centripetal, ``speed**2 / radius``.
- ``polygon``: ``vertices`` (at least 2, consecutive ones distinct), ``speed``; closed (the last
  vertex joins the first). Acceleration is 0 along the edges (the turn at a corner is instant).
- ``spline``: ``points`` (at least 3, consecutive ones distinct), ``speed``: the periodic cubic
  spline through the points (chord-length knots, C2 everywhere, the seam included), re-parameterised
  by arc length; it passes through ``points[0]`` at ``t = 0`` and through every point in order.

Dicts (``to_dict``/:func:`motion_from_dict`) hold plain lists and floats with a ``"type"`` key;
:func:`motion_from_dict` raises :class:`~visfly_dist.errors.ConfigError` naming the bad field.
"""

from __future__ import annotations

import abc
import bisect
import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from visfly_dist.errors import ConfigError

MAX_COORD = 1e4
"""Every coordinate and length lies within +-1e4 m."""
MAX_SPEED = 1e3
MAX_POINTS = 256
MIN_EDGE = 1e-6
"""Consecutive vertices (or spline points) must be at least this far apart, m."""
_GAUSS_X, _GAUSS_W = np.polynomial.legendre.leggauss(8)
_ARC_SUBDIVISIONS = 64     # arc-length table entries per spline segment


@dataclass(frozen=True)
class MotionState:
    """Kinematics along a path for times of shape ``S``: arrays ``S + (3,)``, world frame.

    Attributes:
        position: m. velocity: m/s (tangent, norm ``speed``). acceleration: m/s^2.
    """

    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray


class Motion(abc.ABC):
    """A closed path travelled at constant speed (see the module docstring)."""

    kind: str
    speed: float

    @property
    @abc.abstractmethod
    def length(self) -> float:
        """Length of the closed path, m."""

    @property
    def period(self) -> float:
        """Seconds per lap: ``length / speed``."""
        return self.length / self.speed

    def state(self, t: float | np.ndarray) -> MotionState:
        """Position, velocity and acceleration at times ``t`` (s, any shape; vectorised).

        The answer for the last scalar ``t`` is kept (read-only arrays): a worker's renderer and
        queries ask for the same instant in turn.
        """
        if np.ndim(t) == 0:   # one instant: scalar arithmetic, and the answer kept
            t = float(t)
            last = getattr(self, "_last", None)
            if last is not None and last[0] == t:
                return last[1]
            p, v, a = self._at_one((self.speed * t) % self.length)
            state = MotionState(p, v, a)
            for array in (state.position, state.velocity, state.acceleration):
                array.flags.writeable = False
            self._last = (t, state)
            return state
        t = np.asarray(t, dtype=np.float64)
        p, v, a = self._at_arc(np.mod(self.speed * t.reshape(-1), self.length))
        shape = t.shape + (3,)
        return MotionState(p.reshape(shape), v.reshape(shape), a.reshape(shape))

    def position(self, t: float | np.ndarray) -> np.ndarray:
        """Position at times ``t``, ``t.shape + (3,)``."""
        return self.state(t).position

    def path_points(self, spacing: float) -> np.ndarray:
        """Points ``(m, 3)`` along the whole path at most ``spacing`` m apart (at least 8, corners included)."""
        m = max(8, int(math.ceil(self.length / max(spacing, 1e-3))))
        points = self._at_arc(np.linspace(0.0, self.length, m, endpoint=False))[0]
        return np.concatenate([points, self._corners()])

    def _corners(self) -> np.ndarray:
        return np.zeros((0, 3))

    def _at_one(self, s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`_at_arc` of one arc length: three ``(3,)`` arrays."""
        p, v, a = self._at_arc(np.array([s]))
        return p[0], v[0], a[0]

    @abc.abstractmethod
    def _at_arc(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity, acceleration ``(n, 3)`` at arc lengths ``s (n,)`` in ``[0, length)``."""

    @abc.abstractmethod
    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict with ``"type"``; :func:`motion_from_dict` reads it back."""


class Circle(Motion):
    """A circle of ``radius`` about ``centre`` in the plane normal to ``axis``, from angle ``phase``."""

    kind = "circle"

    def __init__(self, centre, radius: float, speed: float, axis=(0.0, 0.0, 1.0), phase: float = 0.0) -> None:
        self.centre = _vec3(centre, "circle.centre")
        self.radius = _number(radius, "circle.radius", 1e-3, MAX_COORD)
        self.speed = _number(speed, "circle.speed", 1e-6, MAX_SPEED)
        self.axis = _vec3(axis, "circle.axis")
        norm = float(np.linalg.norm(self.axis))
        if norm < 1e-9:
            raise ConfigError(f"circle.axis={self.axis.tolist()} must be a non-zero 3-vector (the circle's normal)")
        self.phase = _number(phase, "circle.phase", -1e6, 1e6)
        n = self.axis / norm
        helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = helper - helper.dot(n) * n
        self._e1 = e1 / np.linalg.norm(e1)
        self._e2 = np.cross(n, self._e1)

    @property
    def length(self) -> float:
        return 2.0 * math.pi * self.radius

    def _at_arc(self, s):
        theta = self.phase + s / self.radius
        c, si = np.cos(theta)[:, None], np.sin(theta)[:, None]
        radial = c * self._e1 + si * self._e2
        tangent = -si * self._e1 + c * self._e2
        return self.centre + self.radius * radial, self.speed * tangent, -(self.speed ** 2 / self.radius) * radial

    def _at_one(self, s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        theta = self.phase + s / self.radius
        c, si = math.cos(theta), math.sin(theta)
        radial = c * self._e1 + si * self._e2
        return (self.centre + self.radius * radial, self.speed * (c * self._e2 - si * self._e1),
                -(self.speed ** 2 / self.radius) * radial)

    def to_dict(self) -> dict[str, Any]:
        return {"type": self.kind, "centre": self.centre.tolist(), "radius": self.radius, "speed": self.speed,
                "axis": self.axis.tolist(), "phase": self.phase}


class Polygon(Motion):
    """The closed polygon through ``vertices`` (last joined to first), from ``vertices[0]``."""

    kind = "polygon"

    def __init__(self, vertices, speed: float) -> None:
        self.vertices = _points(vertices, "polygon.vertices", 2)
        self.speed = _number(speed, "polygon.speed", 1e-6, MAX_SPEED)
        edges = np.roll(self.vertices, -1, axis=0) - self.vertices
        self._edge_lengths = np.linalg.norm(edges, axis=1)
        _check_edges(self._edge_lengths, "polygon.vertices")
        self._units = edges / self._edge_lengths[:, None]
        self._starts = np.concatenate([[0.0], np.cumsum(self._edge_lengths)[:-1]])
        self._starts_list = self._starts.tolist()

    @property
    def length(self) -> float:
        return float(self._edge_lengths.sum())

    def _at_arc(self, s):
        k = np.clip(np.searchsorted(self._starts, s, side="right") - 1, 0, len(self._starts) - 1)
        position = self.vertices[k] + (s - self._starts[k])[:, None] * self._units[k]
        return position, self.speed * self._units[k], np.zeros_like(position)

    def _at_one(self, s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        k = min(max(bisect.bisect_right(self._starts_list, s) - 1, 0), len(self._starts_list) - 1)
        unit = self._units[k]
        return self.vertices[k] + (s - self._starts_list[k]) * unit, self.speed * unit, np.zeros(3)

    def _corners(self) -> np.ndarray:
        return self.vertices

    def to_dict(self) -> dict[str, Any]:
        return {"type": self.kind, "vertices": self.vertices.tolist(), "speed": self.speed}


class Spline(Motion):
    """The periodic cubic spline through ``points``, by arc length, from ``points[0]``.

    Evaluation: arc length -> knot parameter by cubic Hermite interpolation of a table (the exact
    arc length by Gauss-Legendre quadrature at :data:`_ARC_SUBDIVISIONS` sub-knots per segment, with
    its exact derivative ``1 / |C'|``), then the spline and its derivatives at that parameter. So
    positions lie exactly on the spline, ``|velocity| == speed`` to rounding, and the arc-length
    parameterisation is exact to about 1e-8 of a segment.
    """

    kind = "spline"

    def __init__(self, points, speed: float) -> None:
        self.points = _points(points, "spline.points", 3)
        self.speed = _number(speed, "spline.speed", 1e-6, MAX_SPEED)
        chords = np.linalg.norm(np.roll(self.points, -1, axis=0) - self.points, axis=1)
        _check_edges(chords, "spline.points")
        h = chords[:, None]
        m = _periodic_second_derivatives(self.points, chords)
        m_next = np.roll(m, -1, axis=0)
        # segment i: C(tau) = p_i + b tau + c tau^2 + d tau^3, tau in [0, h_i]
        self._coef = np.stack([self.points, (np.roll(self.points, -1, axis=0) - self.points) / h - h * (2 * m + m_next) / 6,
                               m / 2, (m_next - m) / (6 * h)], axis=1)          # (k, 4, 3)
        sub = np.arange(_ARC_SUBDIVISIONS) / _ARC_SUBDIVISIONS
        table_seg = np.append(np.repeat(np.arange(len(chords)), _ARC_SUBDIVISIONS), len(chords) - 1)
        table_tau = np.append((chords[:, None] * sub[None, :]).reshape(-1), chords[-1])
        seg = table_seg[:-1]
        end = np.where(table_seg[1:] == seg, table_tau[1:], chords[seg])   # a segment's last entry ends at its end
        self._table_s = np.concatenate([[0.0], np.cumsum(self._speed_integral(seg, table_tau[:-1], end))])
        slope = 1.0 / np.linalg.norm(self._velocity(table_seg, table_tau), axis=1)   # du/ds
        # per table interval: s0, ds, segment, tau0, dtau, du/ds at both ends
        self._table = np.stack([self._table_s[:-1], np.diff(self._table_s), seg, table_tau[:-1],
                                end - table_tau[:-1], slope[:-1], slope[1:]], axis=1)
        self._table_list_s, self._table_rows = self._table_s.tolist(), [tuple(r) for r in self._table.tolist()]
        self._coef_rows = self._coef.tolist()

    @property
    def length(self) -> float:
        return float(self._table_s[-1])

    def _velocity(self, seg: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """The knot-parameter derivative of segment ``seg`` at ``tau``, ``(n, 3)``."""
        c, t = self._coef[seg], tau[:, None]
        return c[:, 1] + t * (2 * c[:, 2] + 3 * t * c[:, 3])

    def _speed_integral(self, seg: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Arc length of segment ``seg`` between ``tau = lo`` and ``hi``, ``(n,)``."""
        half, mid = (hi - lo) / 2, (hi + lo) / 2
        tau = (mid[:, None] + half[:, None] * _GAUSS_X[None, :]).reshape(-1)
        speed = np.linalg.norm(self._velocity(np.repeat(seg, len(_GAUSS_X)), tau), axis=1).reshape(len(lo), -1)
        return half * (speed @ _GAUSS_W)

    def _at_arc(self, s):
        j = np.clip(np.searchsorted(self._table_s, s, side="right") - 1, 0, len(self._table_s) - 2)
        s0, ds, seg, u0, du, m0, m1 = self._table[j].T
        x = (s - s0) / ds   # cubic Hermite of tau(s) on [s0, s0 + ds]
        x2, x3 = x * x, x * x * x
        tau = (u0 + (3 * x2 - 2 * x3) * du + (x3 - 2 * x2 + x) * ds * m0 + (x3 - x2) * ds * m1)[:, None]
        c = self._coef[seg.astype(np.int64)]
        d2 = 2 * c[:, 2] + 6 * tau * c[:, 3]
        d1 = c[:, 1] + tau * (2 * c[:, 2] + 3 * tau * c[:, 3])
        position = c[:, 0] + tau * (c[:, 1] + tau * (c[:, 2] + tau * c[:, 3]))
        norm2 = np.einsum("ij,ij->i", d1, d1)[:, None]
        tangent = d1 / np.sqrt(norm2)
        normal = d2 - tangent * np.einsum("ij,ij->i", tangent, d2)[:, None]
        return position, self.speed * tangent, (self.speed ** 2) * normal / norm2

    def _at_one(self, s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`_at_arc` of one arc length in Python floats (numpy's per-call cost dominates there)."""
        j = min(max(bisect.bisect_right(self._table_list_s, s) - 1, 0), len(self._table_list_s) - 2)
        s0, ds, seg, u0, du, m0, m1 = self._table_rows[j]
        x = (s - s0) / ds
        x2, x3 = x * x, x * x * x
        tau = u0 + (3 * x2 - 2 * x3) * du + (x3 - 2 * x2 + x) * ds * m0 + (x3 - x2) * ds * m1
        c0, c1, c2, c3 = self._coef_rows[int(seg)]
        p = [c0[a] + tau * (c1[a] + tau * (c2[a] + tau * c3[a])) for a in range(3)]
        d1 = [c1[a] + tau * (2 * c2[a] + 3 * tau * c3[a]) for a in range(3)]
        d2 = [2 * c2[a] + 6 * tau * c3[a] for a in range(3)]
        norm2 = d1[0] * d1[0] + d1[1] * d1[1] + d1[2] * d1[2]
        norm = math.sqrt(norm2)
        t = [d / norm for d in d1]
        along = t[0] * d2[0] + t[1] * d2[1] + t[2] * d2[2]
        k = self.speed ** 2 / norm2
        return (np.array(p), np.array([self.speed * x for x in t]),
                np.array([k * (d2[a] - t[a] * along) for a in range(3)]))

    def _corners(self) -> np.ndarray:
        return self.points

    def to_dict(self) -> dict[str, Any]:
        return {"type": self.kind, "points": self.points.tolist(), "speed": self.speed}


MOTIONS: dict[str, type[Motion]] = {"circle": Circle, "polygon": Polygon, "spline": Spline}
_FIELDS = {"circle": ({"centre", "radius", "speed"}, {"axis", "phase"}),
           "polygon": ({"vertices", "speed"}, set()), "spline": ({"points", "speed"}, set())}


def motion_from_dict(data: Mapping[str, Any], what: str = "motion") -> Motion:
    """The :class:`Motion` a dict describes (the module docstring lists the fields per type).

    Raises:
        ConfigError: not a dict, an unknown type, a missing or unknown field, or a bad value; the
            message names the field (prefixed by ``what``).
    """
    if not isinstance(data, Mapping):
        raise ConfigError(f"{what} must be a dict with a 'type' of {sorted(MOTIONS)}, got {type(data).__name__}")
    kind = data.get("type")
    if kind not in MOTIONS:
        raise ConfigError(f"{what}.type={kind!r} must be one of {sorted(MOTIONS)}")
    required, optional = _FIELDS[kind]
    missing, unknown = sorted(required - set(data)), sorted(set(data) - required - optional - {"type"})
    if missing or unknown:
        raise ConfigError(f"{what} ({kind}): missing field(s) {missing}, unknown field(s) {unknown}; "
                          f"accepted: {sorted(required | optional)}")
    try:
        return MOTIONS[kind](**{k: v for k, v in data.items() if k != "type"})
    except ConfigError as exc:
        raise ConfigError(f"{what}: {exc}") from None


def _number(value: Any, name: str, lo: float, hi: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ConfigError(f"{name}={value!r} must be a number")
    v = float(value)
    if not (math.isfinite(v) and lo <= v <= hi):
        raise ConfigError(f"{name}={value!r} must be finite and in [{lo:g}, {hi:g}]")
    return v


def _vec3(value: Any, name: str) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        v = np.full(0, np.nan)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.any(np.abs(v) > MAX_COORD):
        raise ConfigError(f"{name}={value!r} must be 3 finite numbers within +-{MAX_COORD:g}")
    return v


def _points(value: Any, name: str, minimum: int) -> np.ndarray:
    try:
        p = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        p = np.full(0, np.nan)
    if p.ndim != 2 or p.shape[1] != 3 or not minimum <= len(p) <= MAX_POINTS:
        raise ConfigError(f"{name} must be a list of {minimum} to {MAX_POINTS} [x, y, z] points, got shape {p.shape}")
    if not np.all(np.isfinite(p)) or np.any(np.abs(p) > MAX_COORD):
        raise ConfigError(f"{name} must hold finite coordinates within +-{MAX_COORD:g}")
    return p


def _check_edges(lengths: np.ndarray, name: str) -> None:
    short = np.flatnonzero(lengths < MIN_EDGE)
    if len(short):
        raise ConfigError(f"{name}: point {int(short[0])} and the next one (cyclically) coincide; "
                          f"consecutive points must be at least {MIN_EDGE:g} m apart")


def _periodic_second_derivatives(points: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Second derivatives at the knots ``(k, 3)`` of the periodic cubic spline through ``points``
    with segment lengths ``h`` (segment ``i`` from point ``i`` to ``i + 1 mod k``)."""
    k = len(points)
    prev = np.roll(h, 1)                       # h_{i-1}
    matrix = np.zeros((k, k))
    rows = np.arange(k)
    matrix[rows, rows] = 2.0 * (prev + h)
    np.add.at(matrix, (rows, (rows - 1) % k), prev)
    np.add.at(matrix, (rows, (rows + 1) % k), h)
    slopes = (np.roll(points, -1, axis=0) - points) / h[:, None]
    rhs = 6.0 * (slopes - np.roll(slopes, 1, axis=0))
    return np.linalg.solve(matrix, rhs)
