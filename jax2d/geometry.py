"""Shape checks and mass properties, in plain numpy (used when building scenes, outside jit).

Everything here works in float64; callers cast to float32 when storing into a SimState.
Polygons are convex, counter-clockwise (y up) and have 3..8 vertices.
"""

from __future__ import annotations

import numpy as np

MIN_VERTICES = 3
MAX_VERTICES = 8
# Relative tolerances, scaled by the polygon's size. Vertices closer than this
# fraction of the size are indistinguishable once stored as float32.
_REPEAT_TOL = 1e-6
# Area below this fraction of size^2 is a sliver (collinear points).
_AREA_TOL = 1e-6
# sin(turn) below -this at a vertex makes it reflex; tiny negatives are rounding.
_TURN_TOL = 1e-6


class GeometryError(ValueError):
    """A shape or material value that cannot be simulated."""


def check_positive(value, name: str) -> float:
    """`value` as a float, or GeometryError unless it is finite and > 0."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise GeometryError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(number):
        raise GeometryError(f"{name} must be finite, got {number}")
    if number <= 0:
        raise GeometryError(f"{name} must be > 0, got {number}")
    return number


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def signed_area(vertices: np.ndarray) -> float:
    """Shoelace area: positive for counter-clockwise order."""
    v = np.asarray(vertices, np.float64)
    return 0.5 * float(np.sum(_cross(v, np.roll(v, -1, axis=0))))


def validate_polygon(vertices) -> np.ndarray:
    """Check that `vertices` form a simulable convex polygon; return them as an (n, 2) float64 array."""
    try:
        v = np.array(vertices, dtype=np.float64)
    except (TypeError, ValueError):
        raise GeometryError(f"polygon vertices must be numbers, got {vertices!r}") from None
    if v.ndim != 2 or v.shape[1] != 2:
        raise GeometryError(f"polygon vertices must have shape (n, 2), got {v.shape}")
    n = len(v)
    if not MIN_VERTICES <= n <= MAX_VERTICES:
        raise GeometryError(f"a polygon needs {MIN_VERTICES} to {MAX_VERTICES} vertices, got {n}")
    if not np.all(np.isfinite(v)):
        bad = int(np.nonzero(~np.all(np.isfinite(v), axis=1))[0][0])
        raise GeometryError(f"polygon vertex {bad} is not finite: {v[bad].tolist()}")

    size = float(np.max(np.ptp(v, axis=0)))
    for i in range(n):
        for j in range(i):
            if np.linalg.norm(v[i] - v[j]) <= _REPEAT_TOL * size:
                raise GeometryError(f"polygon vertex {i} repeats vertex {j} ({v[j].tolist()})")

    area = signed_area(v)
    if abs(area) <= _AREA_TOL * size**2:
        raise GeometryError(f"polygon has (near) zero area {area:.3g}: its vertices are collinear or duplicated")
    if area < 0:
        raise GeometryError("vertices must be counter-clockwise (y up); got clockwise order — reverse them")

    incoming = v - np.roll(v, 1, axis=0)  # edge into vertex i
    outgoing = np.roll(v, -1, axis=0) - v  # edge out of vertex i
    lengths = np.linalg.norm(incoming, axis=1) * np.linalg.norm(outgoing, axis=1)
    sin_turn = _cross(incoming, outgoing) / lengths
    if np.any(sin_turn < -_TURN_TOL):
        bad = int(np.nonzero(sin_turn < -_TURN_TOL)[0][0])
        raise GeometryError(f"polygon is not convex: vertex {bad} ({v[bad].tolist()}) turns clockwise")
    # All turns left can still wind twice (a star); a simple convex loop turns exactly 2*pi.
    total_turn = float(np.sum(np.arctan2(_cross(incoming, outgoing), np.sum(incoming * outgoing, axis=1))))
    if total_turn > 2 * np.pi + 1e-6:
        raise GeometryError("polygon is self-intersecting: its vertices wind around more than once")
    return v


def polygon_mass_properties(vertices, density) -> tuple[float, float, np.ndarray]:
    """(mass, moment of inertia about the centroid, centroid) of a uniform convex polygon.

    Fan of triangles (v0, v_i, v_i+1); each triangle's area, centroid and second
    moment about v0 are exact, and they add up because the fan tiles the polygon.
    """
    v = validate_polygon(vertices)
    rho = check_positive(density, "density")
    e1 = v[1:-1] - v[0]
    e2 = v[2:] - v[0]
    areas = 0.5 * _cross(e1, e2)
    area = float(np.sum(areas))
    centroid_from_v0 = np.sum(areas[:, None] * (e1 + e2) / 3.0, axis=0) / area
    # Second moment of a triangle (0, a, b) about 0: area/6 * (a.a + a.b + b.b).
    second_moment_v0 = float(np.sum(areas / 6.0 * (np.sum(e1 * e1, 1) + np.sum(e1 * e2, 1) + np.sum(e2 * e2, 1))))
    mass = rho * area
    inertia = rho * second_moment_v0 - mass * float(centroid_from_v0 @ centroid_from_v0)  # parallel axis
    return mass, inertia, v[0] + centroid_from_v0


def circle_mass_properties(radius, density) -> tuple[float, float, np.ndarray]:
    """(mass, moment of inertia about the centre, centre (0, 0)) of a uniform disc."""
    r = check_positive(radius, "radius")
    rho = check_positive(density, "density")
    mass = np.pi * r * r * rho
    return mass, 0.5 * mass * r * r, np.zeros(2)


def rectangle_vertices(width, height) -> np.ndarray:
    """The (4, 2) counter-clockwise corners of a width x height rectangle centred at the origin."""
    hw = check_positive(width, "width") / 2
    hh = check_positive(height, "height") / 2
    return np.array([[-hw, -hh], [hw, -hh], [hw, hh], [-hw, hh]])


def regular_polygon_vertices(n: int, radius, angle: float = 0.0) -> np.ndarray:
    """(n, 2) counter-clockwise vertices on a circle of `radius` about the origin, the first at `angle`."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not MIN_VERTICES <= n <= MAX_VERTICES:
        raise GeometryError(f"a regular polygon needs an integer {MIN_VERTICES} to {MAX_VERTICES} sides, got {n!r}")
    r = check_positive(radius, "radius")
    theta = float(angle) + 2 * np.pi * np.arange(n) / n
    return r * np.stack([np.cos(theta), np.sin(theta)], axis=1)
