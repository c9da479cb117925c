"""Deterministic scene generators and their registry.

``generate_scene(kind, seed, **params)`` builds a :class:`Scene`; the same kind, seed and params give
identical meshes. Each generator's docstring lists its params; a tuple param is written ``1,0,1.5``
in specs and on the command line. Metadata of every generated scene: ``kind``, ``seed``, ``params``
(all effective values) plus the scene's regions as lists (``start_region`` ``[[low], [high]]``,
``goal``, ...). Segmentation ids follow the object order: 1, 2, ...
"""

from __future__ import annotations

import inspect
from typing import Any, Callable

import numpy as np
import trimesh

from visfly_dist.errors import SceneError
from visfly_dist.scenes.motion import Circle, Motion, Polygon, Spline
from visfly_dist.scenes.primitives import best_candidate, box, colored, shell_boxes, sphere_hits_box, stone, to_float32_grid
from visfly_dist.scenes.scene import Scene, SceneObject

Parts = list[tuple]
"""``(name, mesh)`` per static object, ``(name, mesh in its local frame, motion)`` per moving one."""
Built = tuple[Parts, np.ndarray, dict[str, Any]]

GENERATORS: dict[str, Callable[..., Scene]] = {}

GARAGE_LOW, GARAGE_HIGH = np.array([0.0, -7.0, 0.0]), np.array([18.0, 7.0, 5.0])
MAX_PARAM_ABS = 1e4
"""Every numeric param must lie in [-1e4, 1e4] (scenes are metres across, not light years)."""
MAX_STONE_DENSITY = 1.0
"""At most 1 stone per m^3 (1,260 stones): placement is quadratic in the count, about 0.5 s here."""
MAX_PILLAR_DENSITY = 4.0
"""At most 4 pillars per m^2 of floor (1,008 pillars)."""
MAX_OBSTACLE_RADIUS = 3.0
MAX_MOVING = 100
MAX_MOVING_SPEED = 20.0


def generate_scene(kind: str, seed: int = 0, **params: Any) -> Scene:
    """Build the scene ``kind`` (a key of :data:`GENERATORS`) from ``seed`` and its params.

    Raises:
        SceneError: unknown kind, unknown param, or a value the generator cannot use.
    """
    if kind not in GENERATORS:
        raise SceneError(f"unknown scene kind {kind!r}; valid kinds: {sorted(GENERATORS)}")
    return GENERATORS[kind](seed, **params)


def parse_value(text: str) -> int | float | tuple[float, ...]:
    """A param value from text: int, float, or comma-separated floats (a tuple)."""
    try:
        if "," in text:
            return tuple(float(part) for part in text.split(","))
        return int(text)
    except ValueError:
        try:
            return float(text)
        except ValueError:
            raise SceneError(f"param value {text!r} is not a number or a comma-separated list of numbers") from None


def format_spec(kind: str, seed: int, params: dict[str, Any]) -> str:
    """The canonical ``gen:KIND?seed=S&key=value`` spec (params sorted by name)."""
    def text(value: Any) -> str:
        return ",".join(repr(float(v)) for v in value) if isinstance(value, tuple) else repr(value)

    query = "&".join([f"seed={seed}"] + [f"{key}={text(params[key])}" for key in sorted(params)])
    return f"gen:{kind}?{query}"


def _register(kind: str) -> Callable[[Callable[..., Built]], Callable[..., Scene]]:
    """Register ``build(rng, **params) -> (parts, bounds, regions)`` as generator ``kind``.

    The registered callable ``(seed=0, **params) -> Scene`` checks and coerces the params against the
    builder's keyword defaults, numbers the objects and fills in the metadata.
    """

    def register(build: Callable[..., Built]) -> Callable[..., Scene]:
        defaults = {
            name: p.default for name, p in inspect.signature(build).parameters.items() if p.kind is p.KEYWORD_ONLY
        }

        def generate(seed: int = 0, **given: Any) -> Scene:
            if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
                raise SceneError(f"seed={seed!r} must be an int >= 0")
            values = {**defaults, **_coerce(kind, defaults, given)}
            parts, bounds, regions = build(np.random.default_rng(int(seed)), **values)
            objects = [SceneObject(name, i, to_float32_grid(mesh), motion[0] if motion else None)
                       for i, (name, mesh, *motion) in enumerate(parts, start=1)]
            metadata = {"kind": kind, "seed": int(seed), "params": {k: _plain(v) for k, v in values.items()}}
            metadata.update({k: _plain(v) for k, v in regions.items()})
            return Scene(format_spec(kind, int(seed), _coerce(kind, defaults, given)), objects, bounds, metadata)

        generate.__name__ = build.__name__
        generate.__doc__ = build.__doc__
        generate.params = defaults  # type: ignore[attr-defined]
        GENERATORS[kind] = generate
        return generate

    return register


def _coerce(kind: str, defaults: dict[str, Any], given: dict[str, Any]) -> dict[str, Any]:
    unknown = sorted(set(given) - set(defaults))
    if unknown:
        raise SceneError(f"unknown param(s) {unknown} for scene kind {kind!r}; valid params: {sorted(defaults)}")
    out: dict[str, Any] = {}
    for key, value in given.items():
        default = defaults[key]
        try:
            if isinstance(default, tuple):
                value = tuple(float(v) for v in (value if isinstance(value, (tuple, list, np.ndarray)) else (value,)))
                ok = len(value) == len(default)
            elif isinstance(default, int):
                ok = float(value) == int(value)
                value = int(value)
            else:
                value = float(value)
                ok = True
        except (TypeError, ValueError):
            ok = False
        if not ok or not np.all(np.isfinite(value)):
            raise SceneError(f"param {key}={given[key]!r} of scene kind {kind!r} must be like the default {default!r}")
        if np.any(np.abs(value) > MAX_PARAM_ABS):
            raise SceneError(f"param {key}={given[key]!r} of scene kind {kind!r} must lie in "
                             f"[{-MAX_PARAM_ABS:g}, {MAX_PARAM_ABS:g}]")
        out[key] = value
    return out


def _plain(value: Any) -> Any:
    """JSON-able copy: arrays and tuples become lists, numpy scalars Python numbers."""
    if isinstance(value, (np.ndarray, tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise SceneError(message)


def _region(name: str, center: tuple[float, ...], half: tuple[float, ...]) -> np.ndarray:
    """``[low, high]`` of the box ``center ± half``, which must lie inside the garage (a start or
    goal outside it has no floor, no walls in view and no way in)."""
    _check(all(h >= 0 for h in half), f"{name}_half {half} must be >= 0")
    low, high = np.subtract(center, half), np.add(center, half)
    _check(bool(np.all(low >= GARAGE_LOW) and np.all(high <= GARAGE_HIGH)),
           f"{name}_center {tuple(center)} ± {name}_half {tuple(half)} must lie inside the garage "
           f"{GARAGE_LOW.tolist()}..{GARAGE_HIGH.tolist()} m")
    return np.array([low, high])


@_register("garage-stones")
def garage_stones(
    rng: np.random.Generator,
    *,
    density: float = 0.15,
    min_radius: float = 0.2,
    max_radius: float = 0.6,
    start_center: tuple[float, ...] = (1.0, 0.0, 1.5),
    start_half: tuple[float, ...] = (1.0, 2.0, 1.0),
    goal_center: tuple[float, ...] = (9.0, 0.0, 1.0),
    goal_half: tuple[float, ...] = (0.5, 0.5, 0.5),
    margin: float = 0.2,
    moving: int = 0,
    moving_speed: float = 1.0,
) -> Built:
    """An 18 x 14 x 5 m garage, bounds [0,-7,0]..[18,7,5], cluttered with random stones.

    Params:
        density: stones per cubic metre of interior (count = round(volume * density)).
        min_radius, max_radius: range of each stone's bounding radius, m.
        start_center, start_half: start region (centre, half extents), kept clear of stones.
        goal_center, goal_half: goal region, kept clear of stones.
        margin: extra free space around both regions, m.
        moving: number of moving stones (at most 100), each on a random circle, polygon or spline
            (:mod:`visfly_dist.scenes.motion`) whose swept path keeps clear of both regions.
        moving_speed: mean speed of the moving stones, m/s (each gets 0.7 to 1.3 times it).

    Metadata: ``start_region``, ``goal_region`` ([[low], [high]]), ``goal`` (the goal centre),
    ``num_stones``, ``moving_objects`` (when ``moving`` > 0). Objects: floor, ceiling, four walls,
    then ``stone_000``..., then ``moving_stone_000``... (drawn after the static stones, so ``moving``
    leaves the rest of the scene as it was).
    """
    _check(0 <= density <= MAX_STONE_DENSITY, f"density={density} must be in [0, {MAX_STONE_DENSITY}] stones per m^3")
    _check(0 < min_radius <= max_radius <= MAX_OBSTACLE_RADIUS,
           f"min_radius={min_radius}, max_radius={max_radius} must satisfy 0 < min <= max <= {MAX_OBSTACLE_RADIUS}")
    _check(margin >= 0, f"margin={margin} must be >= 0")
    start, goal = _region("start", start_center, start_half), _region("goal", goal_center, goal_half)
    count = int(round(float(np.prod(GARAGE_HIGH - GARAGE_LOW)) * density))
    radii = rng.uniform(min_radius, max_radius, size=count)
    keep_clear = [(r[0] - margin, r[1] + margin) for r in (start, goal)]
    centers = best_candidate(rng, radii, GARAGE_LOW, GARAGE_HIGH, keep_clear)
    parts: Parts = [*shell_boxes(GARAGE_LOW, GARAGE_HIGH)]
    parts += [(f"stone_{i:03d}", stone(rng, c, r)) for i, (c, r) in enumerate(zip(centers, radii))]
    _check(0 <= moving <= MAX_MOVING, f"moving={moving} must be in [0, {MAX_MOVING}]")
    _check(0 < moving_speed <= MAX_MOVING_SPEED, f"moving_speed={moving_speed} must be in (0, {MAX_MOVING_SPEED}] m/s")
    for i in range(moving):
        radius = rng.uniform(min_radius, max_radius)
        motion = _clear_path(rng, radius, moving_speed, keep_clear)
        parts.append((f"moving_stone_{i:03d}", stone(rng, np.zeros(3), radius), motion))
    regions = {"start_region": start, "goal_region": goal, "goal": goal_center, "num_stones": count}
    return parts, np.array([GARAGE_LOW, GARAGE_HIGH]), regions


def _clear_path(rng: np.random.Generator, radius: float, speed: float, keep_clear, rounds: int = 100) -> Motion:
    """A random circle, polygon or spline inside the garage whose swept sphere misses ``keep_clear``."""
    low, high = GARAGE_LOW + radius + 0.3, GARAGE_HIGH - radius - 0.3
    for _ in range(rounds):
        centre = rng.uniform(low, high)
        kind = int(rng.integers(3))
        speed_k = speed * rng.uniform(0.7, 1.3)
        if kind == 0:
            r = rng.uniform(1.0, 3.0)
            centre[:2] = np.clip(centre[:2], low[:2] + r, high[:2] - r)
            motion: Motion = Circle(centre, r, speed_k, phase=rng.uniform(0, 2 * np.pi))
        else:
            k = int(rng.integers(3, 6))
            angles = np.sort(rng.uniform(0, 2 * np.pi, k))
            reach = rng.uniform(1.0, 3.0, k)
            points = centre + np.stack([reach * np.cos(angles), reach * np.sin(angles), rng.uniform(-0.5, 0.5, k)], axis=1)
            points = np.clip(points, low, high)
            if np.min(np.linalg.norm(np.roll(points, -1, axis=0) - points, axis=1)) < 0.1:
                continue
            motion = Polygon(points, speed_k) if kind == 1 else Spline(points, speed_k)
        swept = motion.path_points(0.1)
        if np.all((swept >= GARAGE_LOW + radius) & (swept <= GARAGE_HIGH - radius)) and not any(
                sphere_hits_box(swept, radius, box_low, box_high).any() for box_low, box_high in keep_clear):
            return motion
    raise SceneError(f"no path for a moving stone of radius {radius:.2f} m clear of the regions {keep_clear}; "
                     "shrink the regions or lower `moving`")


@_register("gap-walls")
def gap_walls(
    rng: np.random.Generator,
    *,
    gap_width: float = 0.8,
    wall_x: float = 8.0,
    gap_y: float = 0.0,
    gap_y_spread: float = 0.0,
    wall_thickness: float = 0.2,
) -> Built:
    """The 18 x 14 x 5 m garage split by a wall across x with one floor-to-ceiling gap.

    Params:
        gap_width: width of the vertical gap, m.
        wall_x: x of the wall's centre plane, m.
        gap_y: y of the gap's centre, m.
        gap_y_spread: the gap's centre is drawn uniformly in ``gap_y ± gap_y_spread`` from the
            scene's seed (0: exactly ``gap_y``), so a set of seeds gives walls a policy has not seen.
        wall_thickness: wall thickness along x, m.

    Metadata: ``gap_center`` ([wall_x, gap_y, mid-height]), ``start_region`` (before the wall),
    ``goal`` ([13, 0, 1.5]) and ``targets`` (three goals at y = -2, 0, 2 for a team).
    Objects: the garage shell, then ``wall_left`` (y < gap) and ``wall_right``.
    """
    (x0, y0, z0), (x1, y1, z1) = GARAGE_LOW, GARAGE_HIGH
    half_gap, half_t = gap_width / 2, wall_thickness / 2
    _check(gap_y_spread >= 0 and y0 < gap_y - gap_y_spread - half_gap and gap_y + gap_y_spread + half_gap < y1,
           f"gap_y={gap_y} ± gap_y_spread={gap_y_spread} with gap_width={gap_width} must leave wall on both sides "
           f"within y in ({y0}, {y1})")
    gap_y = float(gap_y + rng.uniform(-gap_y_spread, gap_y_spread)) if gap_y_spread > 0 else gap_y
    _check(gap_width > 0 and y0 < gap_y - half_gap and gap_y + half_gap < y1,
           f"gap_width={gap_width}, gap_y={gap_y} must leave wall on both sides within y in ({y0}, {y1})")
    _check(wall_thickness > 0 and x0 < wall_x - half_t and wall_x + half_t < x1,
           f"wall_x={wall_x}, wall_thickness={wall_thickness} must put the wall inside x in ({x0}, {x1})")
    color = (170, 60, 50)
    parts: Parts = [*shell_boxes(GARAGE_LOW, GARAGE_HIGH)]
    parts.append(("wall_left", box((wall_x - half_t, y0, z0), (wall_x + half_t, gap_y - half_gap, z1), color)))
    parts.append(("wall_right", box((wall_x - half_t, gap_y + half_gap, z0), (wall_x + half_t, y1, z1), color)))
    regions = {
        "gap_center": [wall_x, gap_y, (z0 + z1) / 2],
        "start_region": [[1.0, -3.0, 1.0], [3.0, 3.0, 2.0]],
        "goal": [13.0, 0.0, 1.5],
        "targets": [[13.0, -2.0, 1.5], [13.0, 0.0, 1.5], [13.0, 2.0, 1.5]],
    }
    return parts, np.array([GARAGE_LOW, GARAGE_HIGH]), regions


@_register("landing-pad")
def landing_pad(
    rng: np.random.Generator,
    *,
    pad_x: float = 2.0,
    pad_y: float = 0.0,
    pad_size: float = 0.5,
    pad_height: float = 0.01,
) -> Built:
    """A grey floor with a black square landing pad; bounds [-3,-5,0]..[7,5,5].

    Params:
        pad_x, pad_y: centre of the pad on the floor, m.
        pad_size: side of the square pad, m.
        pad_height: thickness of the pad above the floor, m.

    Metadata: ``pad_center`` ([pad_x, pad_y, 0]), ``pad_size``, ``start_region`` (pad ± 1 m, 1.5-3.5 m up).
    Objects: ``floor`` (id 1), ``pad`` (id 2, black).
    """
    low, high = np.array([-3.0, -5.0, 0.0]), np.array([7.0, 5.0, 5.0])
    half = pad_size / 2
    _check(pad_size > 0 and pad_height > 0, f"pad_size={pad_size}, pad_height={pad_height} must be > 0")
    _check(low[0] <= pad_x - half and pad_x + half <= high[0] and low[1] <= pad_y - half and pad_y + half <= high[1],
           f"pad at ({pad_x}, {pad_y}) size {pad_size} must lie within x {low[0]}..{high[0]}, y {low[1]}..{high[1]}")
    floor = box((low[0], low[1], -0.1), (high[0], high[1], 0.0), (150, 150, 145))
    pad = box((pad_x - half, pad_y - half, 0.0), (pad_x + half, pad_y + half, pad_height), (0, 0, 0))
    regions = {
        "pad_center": [pad_x, pad_y, 0.0],
        "pad_size": pad_size,
        "start_region": [[pad_x - 1.0, pad_y - 1.0, 1.5], [pad_x + 1.0, pad_y + 1.0, 3.5]],
    }
    return [("floor", floor), ("pad", pad)], np.array([low, high]), regions


@_register("pillars")
def pillars(
    rng: np.random.Generator,
    *,
    density: float = 0.12,
    min_radius: float = 0.15,
    max_radius: float = 0.4,
    start_center: tuple[float, ...] = (1.0, 0.0, 1.5),
    start_half: tuple[float, ...] = (1.0, 2.0, 1.0),
    goal_center: tuple[float, ...] = (16.0, 0.0, 1.5),
    goal_half: tuple[float, ...] = (0.5, 0.5, 0.5),
    margin: float = 0.2,
) -> Built:
    """A forest of floor-to-ceiling cylinders in the 18 x 14 x 5 m garage.

    Params:
        density: pillars per square metre of floor (count = round(area * density)).
        min_radius, max_radius: range of pillar radii, m.
        start_center, start_half, goal_center, goal_half: regions kept clear (in x and y).
        margin: extra free space around both regions, m.

    Metadata: ``start_region``, ``goal_region``, ``goal``, ``num_pillars``.
    Objects: the garage shell, then ``pillar_000``...
    """
    _check(0 <= density <= MAX_PILLAR_DENSITY, f"density={density} must be in [0, {MAX_PILLAR_DENSITY}] pillars per m^2")
    _check(0 < min_radius <= max_radius <= MAX_OBSTACLE_RADIUS,
           f"min_radius={min_radius}, max_radius={max_radius} must satisfy 0 < min <= max <= {MAX_OBSTACLE_RADIUS}")
    start, goal = _region("start", start_center, start_half), _region("goal", goal_center, goal_half)
    area = float(np.prod((GARAGE_HIGH - GARAGE_LOW)[:2]))
    count = int(round(area * density))
    radii = rng.uniform(min_radius, max_radius, size=count)
    height = GARAGE_HIGH[2] - GARAGE_LOW[2]
    # Pillars span the full height: centres on the mid-height plane, regions extruded to all z.
    keep_clear = [(np.append(r[0][:2] - margin, -np.inf), np.append(r[1][:2] + margin, np.inf)) for r in (start, goal)]
    plane_low, plane_high = GARAGE_LOW.copy(), GARAGE_HIGH.copy()
    plane_low[2] = plane_high[2] = GARAGE_LOW[2] + height / 2
    centers = best_candidate(rng, radii, plane_low, plane_high, keep_clear)
    parts: Parts = [*shell_boxes(GARAGE_LOW, GARAGE_HIGH)]
    for i, (center, radius) in enumerate(zip(centers, radii)):
        cylinder = trimesh.creation.cylinder(
            radius=radius, height=height, sections=16, transform=trimesh.transformations.translation_matrix(center)
        )
        parts.append((f"pillar_{i:03d}", colored(cylinder, (90, 110, 140), rng, jitter=10)))
    regions = {"start_region": start, "goal_region": goal, "goal": goal_center, "num_pillars": count}
    return parts, np.array([GARAGE_LOW, GARAGE_HIGH]), regions


@_register("empty")
def empty(rng: np.random.Generator) -> Built:
    """A floor only, bounds [-10,-10,0]..[10,10,10]; for hovering. No params.

    Metadata: ``start_region`` ([[-1,-1,0.5], [1,1,1.5]]) and ``goal`` ([1, 0, 1.5]).
    """
    low, high = np.array([-10.0, -10.0, 0.0]), np.array([10.0, 10.0, 10.0])
    floor = box((low[0], low[1], -0.1), (high[0], high[1], 0.0), (130, 135, 130))
    regions = {"start_region": [[-1.0, -1.0, 0.5], [1.0, 1.0, 1.5]], "goal": [1.0, 0.0, 1.5]}
    return [("floor", floor)], np.array([low, high]), regions
