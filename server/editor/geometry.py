"""Plane geometry on `BodySpec`s in world coordinates: outlines, hit tests, convexity, frames.

Everything is plain Python floats: the editor edits a handful of shapes per user action, so
numpy or JAX would only add start-up cost.
"""

from __future__ import annotations

import math

from kinetix.formats import BodySpec

Point = tuple[float, float]


def rotate(v: Point, angle: float) -> Point:
    c, s = math.cos(angle), math.sin(angle)
    return (c * v[0] - s * v[1], s * v[0] + c * v[1])


def to_world(body: BodySpec, local: Point) -> Point:
    x, y = rotate(local, body.angle)
    return (body.position[0] + x, body.position[1] + y)


def to_local(body: BodySpec, world: Point) -> Point:
    return rotate((world[0] - body.position[0], world[1] - body.position[1]), -body.angle)


def world_vertices(body: BodySpec) -> list[Point]:
    return [to_world(body, (float(v[0]), float(v[1]))) for v in body.vertices or []]


def contains(body: BodySpec, p: Point) -> bool:
    if body.shape == "circle":
        return math.dist(body.position, p) <= body.radius
    pts = world_vertices(body)
    # Convex and counter-clockwise: inside means left of (or on) every edge.
    return all(cross(a, b, p) >= -1e-12 for a, b in zip(pts, pts[1:] + pts[:1], strict=True))


def cross(o: Point, a: Point, b: Point) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def bounds(body: BodySpec) -> tuple[float, float, float, float]:
    if body.shape == "circle":
        (x, y), r = body.position, body.radius
        return (x - r, y - r, x + r, y + r)
    pts = world_vertices(body)
    xs, ys = [p[0] for p in pts], [p[1] for p in pts]
    return (min(xs), min(ys), max(xs), max(ys))


def signed_area(points: list[Point]) -> float:
    return 0.5 * sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(points, points[1:] + points[:1], strict=True))


def convexity_error(points: list[Point]) -> str | None:
    """Why these vertices (in either winding) are not a strictly convex polygon, else None."""
    n = len(points)
    if n < 3:
        return f"a polygon needs at least 3 vertices, got {n}"
    if abs(signed_area(points)) < 1e-6:
        return "polygon has no area"
    turns = [cross(points[i], points[(i + 1) % n], points[(i + 2) % n]) for i in range(n)]
    if not (all(t > 1e-12 for t in turns) or all(t < -1e-12 for t in turns)):
        return "polygon is not convex"
    # All turns one way can still wind round twice (a star); the angles must sum to one turn.
    total = 0.0
    for i in range(n):
        a, b, c = points[i], points[(i + 1) % n], points[(i + 2) % n]
        total += math.atan2(cross(a, b, c), (b[0] - a[0]) * (c[0] - b[0]) + (b[1] - a[1]) * (c[1] - b[1]))
    if abs(abs(total) - 2 * math.pi) > 1e-6:
        return "polygon is not convex"
    return None


def centroid(points: list[Point]) -> Point:
    area = signed_area(points)
    cx = cy = 0.0
    for a, b in zip(points, points[1:] + points[:1], strict=True):
        w = a[0] * b[1] - b[0] * a[1]
        cx += (a[0] + b[0]) * w
        cy += (a[1] + b[1]) * w
    return (cx / (6 * area), cy / (6 * area))


def polygon_body(points: list[Point], path: str = "") -> BodySpec:
    """A polygon body at its centroid, vertices counter-clockwise in the body frame."""
    if signed_area(points) < 0:
        points = points[::-1]
    cx, cy = centroid(points)
    return BodySpec(path=path, shape="polygon", position=(cx, cy),
                    vertices=[[x - cx, y - cy] for x, y in points])


def outline(body: BodySpec) -> dict:
    """The body's outline as an Overlay shape dict."""
    if body.shape == "circle":
        return {"kind": "circle", "center": tuple(body.position), "radius": body.radius}
    return {"kind": "polygon", "points": world_vertices(body)}


def segment_distance(p: Point, a: Point, b: Point) -> float:
    dx, dy = b[0] - a[0], b[1] - a[1]
    length2 = dx * dx + dy * dy
    t = 0.0 if length2 == 0 else max(0.0, min(1.0, ((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / length2))
    return math.dist(p, (a[0] + t * dx, a[1] + t * dy))
