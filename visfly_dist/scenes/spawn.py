"""Sampling spawn positions that keep a clearance from every obstacle."""

from __future__ import annotations

from typing import Callable

import numpy as np

from visfly_dist.errors import SceneError

DISTRIBUTIONS = ("uniform", "normal")
NO_ROOM_CLEARANCE_M = 0.1
"""A flight box thinner than twice this along an axis is flat: no spawn clearance leaves room in it."""


def sample_free_positions(
    n: int,
    clearance: float,
    distribution: str,
    a,
    b,
    rng: np.random.Generator,
    distance_fn: Callable[[np.ndarray], np.ndarray],
    bounds=None,
    max_tries: int = 100_000,
) -> np.ndarray:
    """Draw ``n`` positions whose obstacle distance is at least ``clearance``, by batched rejection.

    Args:
        n: number of positions.
        clearance: minimum distance to any obstacle, m (also kept from the bounds' faces).
        distribution: ``"uniform"`` (``a`` = low, ``b`` = high corner) or ``"normal"`` (``a`` =
            mean, ``b`` = standard deviation per axis). ``a`` and ``b`` are 3-vectors or scalars.
        a, b: the distribution's parameters (see above).
        rng: source of randomness; the same state gives the same positions.
        distance_fn: ``(m, 3) -> (m,)`` distance from each point to the nearest obstacle (negative
            or zero inside or touching one).
        bounds: optional ``(2, 3)`` flight box; positions stay ``clearance`` inside it.
        max_tries: how many candidate points may be drawn in all.

    Returns:
        ``(n, 3)`` float64 positions, in the order they were drawn.

    Raises:
        SceneError: bad arguments, or fewer than ``n`` free positions found within ``max_tries``.
    """
    a, b = _vector(a, "a"), _vector(b, "b")
    if distribution not in DISTRIBUTIONS:
        raise SceneError(f"distribution={distribution!r} is not supported; use one of {list(DISTRIBUTIONS)}")
    if distribution == "uniform" and np.any(b < a):
        raise SceneError(f"uniform spawn needs low a={a.tolist()} <= high b={b.tolist()}")
    if distribution == "normal" and np.any(b < 0):
        raise SceneError(f"normal spawn needs std b={b.tolist()} >= 0")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise SceneError(f"n={n!r} must be an int >= 0")
    if not (np.isfinite(clearance) and clearance >= 0):
        raise SceneError(f"clearance={clearance!r} must be a finite number >= 0")
    box = None
    if bounds is not None:
        bounds = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
        box = (bounds[0] + clearance, bounds[1] - clearance)
        if np.any(box[0] > box[1]):
            extent = bounds[1] - bounds[0]
            short = [f"{axis} ({e:g} m)" for axis, e, lo, hi in zip("xyz", extent, *box) if lo > hi]
            if np.any(extent < 2 * NO_ROOM_CLEARANCE_M):  # flat: no clearance would help
                raise SceneError(
                    f"the scene's flight box {bounds.tolist()} has no room to fly along {', '.join(short)}; a mesh "
                    "file's flight box is its bounding box: add the scene's walls or ceiling to the file, or save it "
                    "as a scene directory whose scene.json gives its bounds (visfly_dist.scenes.save_scene)")
            raise SceneError(f"bounds {bounds.tolist()} shrunk by clearance={clearance} leave no room along "
                             f"{', '.join(short)}; lower the clearance")

    where = (f"{distribution} region a={a.tolist()}, b={b.tolist()}"
             + (f" within bounds {bounds.tolist()}" if bounds is not None else ""))
    if n == 0:
        return np.zeros((0, 3))
    _refuse_impossible(n, clearance, distribution, a, b, box, distance_fn, where)

    found: list[np.ndarray] = []
    count = tried = outside = close = inside = 0
    farthest = -np.inf
    while count < n and tried < max_tries:
        batch = int(min(max_tries - tried, max(64, 4 * (n - count))))
        points = rng.uniform(a, b, size=(batch, 3)) if distribution == "uniform" else rng.normal(a, b, size=(batch, 3))
        tried += batch
        keep = np.ones(batch, dtype=bool)
        if box is not None:
            keep &= np.all((points >= box[0]) & (points <= box[1]), axis=1)
            outside += batch - int(keep.sum())
        if keep.any():
            distance = np.asarray(distance_fn(points[keep]), dtype=np.float64).reshape(-1)
            clear = distance >= clearance
            close += int((~clear).sum())
            inside += int((distance <= 0).sum())
            farthest = max(farthest, float(distance.max()))
            keep[keep] = clear
        found.append(points[keep])
        count += int(keep.sum())
    if count < n:
        reasons = []
        if outside:
            reasons.append(f"{outside} fell outside the flight box (bounds shrunk by the clearance)")
        if close:
            reasons.append(f"{close} were closer than the clearance to an obstacle ({inside} of them inside one; "
                           f"the farthest drawn point was {farthest:.3g} m from any obstacle)")
        raise SceneError(
            f"found only {count} of {n} positions with clearance={clearance} m in {where} after {tried} tries: "
            + "; ".join(reasons) + "; widen the region, lower the clearance, or raise max_tries"
        )
    return np.concatenate(found)[:n]


GRID_CELLS = 8
"""Cells per axis of the grid that :func:`_refuse_impossible` checks a uniform region with."""


def _refuse_impossible(n: int, clearance: float, distribution: str, a: np.ndarray, b: np.ndarray, box,
                       distance_fn: Callable[[np.ndarray], np.ndarray], where: str) -> None:
    """SceneError before any draw when no draw can succeed, naming the constraint.

    Two cases are provable: the region misses the flight box on an axis (a target above the scene),
    and, for a uniform region, every point of it lies within the clearance of obstacles. The
    second uses that a distance to obstacles changes by at most the distance moved: the region is
    cut into a grid, and a cell whose centre is ``d`` from obstacles holds no point farther than
    ``|d| +`` its half-diagonal.
    """
    head = f"found only 0 of {n} positions with clearance={clearance} m in {where}: "
    axes = "xyz"
    if box is not None:
        if distribution == "uniform":
            low, high = np.maximum(a, box[0]), np.minimum(b, box[1])
            for i in np.flatnonzero(low > high):
                raise SceneError(head + f"the region ({axes[i]} in [{a[i]:g}, {b[i]:g}]) lies outside the flight box "
                                 f"({axes[i]} in [{box[0][i]:g}, {box[1][i]:g}], the bounds shrunk by the clearance) "
                                 f"on axis {axes[i]}; move the region into the scene's bounds")
            a, b = low, high
        else:
            for i in np.flatnonzero((b == 0) & ((a < box[0]) | (a > box[1]))):
                raise SceneError(head + f"the mean {axes[i]}={a[i]:g} with std 0 lies outside the flight box "
                                 f"({axes[i]} in [{box[0][i]:g}, {box[1][i]:g}], the bounds shrunk by the clearance) "
                                 f"on axis {axes[i]}; move the mean into the scene's bounds")
    if distribution != "uniform" or clearance <= 0:
        return
    cells = np.where(b > a, GRID_CELLS, 1)
    size = (b - a) / cells
    grids = np.meshgrid(*[a[i] + size[i] * (np.arange(cells[i]) + 0.5) for i in range(3)], indexing="ij")
    centres = np.stack([g.ravel() for g in grids], axis=1)
    reach = np.abs(np.asarray(distance_fn(centres), dtype=np.float64).reshape(-1)) + 0.5 * float(np.linalg.norm(size))
    if np.all(reach < clearance):
        raise SceneError(head + f"every point of the region lies within the clearance of obstacles (none can be "
                         f"farther than {float(reach.max()):.3g} m from one); move the region or lower the clearance")


def _vector(value, name: str) -> np.ndarray:
    try:
        vector = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        vector = np.full(0, np.nan)
    if vector.ndim == 0:
        vector = np.full(3, float(vector))
    if vector.shape != (3,) or not np.all(np.isfinite(vector)):
        raise SceneError(f"{name}={value!r} must be a finite scalar or 3-vector")
    return vector
