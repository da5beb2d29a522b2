"""Snapping a pointer position to features of the level (vertices, body centres, edge midpoints) or the grid.

A point near a feature snaps onto it; otherwise each axis snaps to a feature coordinate it is close
to (the alignment guides of drawing programs); what is left snaps to the grid. The guides are the
lines the renderer draws to show why the point ended where it did.
"""

from __future__ import annotations

import math

from kinetix.formats import BodySpec
from server.editor.geometry import Point, world_vertices

WORLD = (0.0, 0.0, 5.0, 5.0)  # extent of the guide lines


def features(bodies: list[tuple[int, BodySpec]]) -> list[Point]:
    points = []
    for _, body in bodies:
        points.append(tuple(body.position))
        if body.shape == "polygon":
            pts = world_vertices(body)
            points += pts
            points += [((a[0] + b[0]) / 2, (a[1] + b[1]) / 2) for a, b in zip(pts, pts[1:] + pts[:1], strict=True)]
        else:
            (x, y), r = body.position, body.radius
            points += [(x + r, y), (x - r, y), (x, y + r), (x, y - r)]
    return points


def snap(p: Point, bodies: list[tuple[int, BodySpec]], grid: float, tolerance: float = 0.08
         ) -> tuple[Point, list[tuple[float, float, float, float]], Point | None]:
    """(snapped point, guide lines, the feature snapped to or None)."""
    x0, y0, x1, y1 = WORLD
    points = features(bodies)
    near = min(points, key=lambda q: math.dist(p, q), default=None)
    if near is not None and math.dist(p, near) <= tolerance:
        return near, [(x0, near[1], x1, near[1]), (near[0], y0, near[0], y1)], near
    x, y = p
    guides = []
    xs = [q for q in points if abs(q[0] - p[0]) <= tolerance]
    ys = [q for q in points if abs(q[1] - p[1]) <= tolerance]
    if xs:
        x = min(xs, key=lambda q: abs(q[0] - p[0]))[0]
        guides.append((x, y0, x, y1))
    elif grid > 0:
        x = round(p[0] / grid) * grid
    if ys:
        y = min(ys, key=lambda q: abs(q[1] - p[1]))[1]
        guides.append((x0, y, x1, y))
    elif grid > 0:
        y = round(p[1] / grid) * grid
    return (x, y), guides, None
