"""Polygons of 5-8 vertices as welded triangles and quadrilaterals, for export to the public Kinetix.

Their loader only opens files whose `max_polygon_vertices` is 4 and their collision code reads only 4 vertex
slots (docs/level-format.md, "Export"), so export cuts each bigger convex polygon along diagonals into parts of
3-4 vertices. The parts keep the polygon's role, density, material and collision mode; each sits at its own
centroid with the polygon's angle and the velocity of that point of the polygon, so together they have the
polygon's mass, centre of mass, inertia and momentum. Parts that share a diagonal are welded (a fixed joint
anchored at the diagonal's midpoint); in both engines bodies linked by a chain of joints never collide, so the
parts never collide with each other, and a body jointed to the polygon collides with none of them. Joints and
thrusters on the polygon move to the part under their anchor (the largest part if the anchor is outside the
polygon), with the anchor in that part's frame.

A fixed polygon with no joints is not welded: its parts never move, and fixed bodies never collide with each
other, so welds would only spend joint slots.

A motor's torque limit is its power times the axial mass 1 / (1/I_a + 1/I_b) of the bodies it joins (in both
engines), so on a part (smaller inertia than the whole polygon) the motor would get weaker; its power is scaled
by (1/I_a' + 1/I_b') / (1/I_a + 1/I_b) to keep the limit of the original motor.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from collections.abc import Iterator

import numpy as np

from jax2d.geometry import (
    GeometryError,
    circle_mass_properties,
    polygon_mass_properties,
    signed_area,
    validate_polygon,
)
from kinetix import ranges
from kinetix.formats import BodySpec, JointSpec, LevelSpec
from kinetix.level import LevelError

MAX_PART_VERTICES = 4  # what their engine collides and their loader accepts


@dataclasses.dataclass(frozen=True)
class SplitPolygon:
    """One polygon that export split."""

    body: int  # its index in the level's bodies
    path: str  # its name in messages, e.g. "bodies[5]"
    vertices: int
    parts: tuple[int, ...]  # body indices of its parts in the split spec; the first is `body` itself
    welds: int  # fixed joints added between its parts


@dataclasses.dataclass
class Split:
    spec: LevelSpec  # the level with every polygon of at most MAX_PART_VERTICES vertices
    polygons: list[SplitPolygon]
    motor_scale: dict[int, float]  # joint index -> factor its motor power was multiplied by

    @property
    def welds(self) -> int:
        return sum(p.welds for p in self.polygons)

    def summary(self) -> str:
        """What was split, in words (empty if nothing): "split 2 polygons (8 and 6 vertices) into 5 parts welded
        by 3 fixed joints"."""
        if not self.polygons:
            return ""
        n = len(self.polygons)
        counts = [str(p.vertices) for p in self.polygons]
        listed = counts[0] if n == 1 else ", ".join(counts[:-1]) + " and " + counts[-1]
        parts = sum(len(p.parts) for p in self.polygons)
        text = f"split {n} polygon{'s' * (n > 1)} ({listed} vertices) into {parts} parts"
        if self.welds:
            text += f" welded by {self.welds} fixed joint{'s' * (self.welds != 1)}"
        unwelded = sum(p.welds == 0 for p in self.polygons)
        if unwelded == n:
            text += " (not welded: a fixed polygon without joints never moves)"
        elif unwelded:
            text += (f" (the parts of {unwelded} fixed polygon{'s' * (unwelded > 1)} without joints are not welded: "
                     "they never move)")
        return text


# ---------------------------------------------------------------- cutting one polygon


def _dissections(ring: tuple[int, ...]) -> Iterator[list[tuple[int, ...]]]:
    """Every way to cut the convex polygon `ring` (vertex indices, counter-clockwise) along diagonals into parts
    of 3 or 4 vertices. The part holding edge ring[0]-ring[1] is that edge plus one or two later vertices; what
    it leaves are smaller convex polygons, cut the same way."""
    m = len(ring)
    if m <= MAX_PART_VERTICES:
        yield [ring]
        return
    for extra in itertools.chain(((k,) for k in range(2, m)), itertools.combinations(range(2, m), 2)):
        corners = (0, 1, *extra)
        rest = [ring[corners[i]:corners[i + 1] + 1] for i in range(1, len(corners) - 1)]
        rest.append(ring[corners[-1]:] + ring[:1])
        rest = [piece for piece in rest if len(piece) >= 3]
        part = tuple(ring[c] for c in corners)
        for cuts in itertools.product(*(list(_dissections(piece)) for piece in rest)):
            yield [part, *itertools.chain.from_iterable(cuts)]


@functools.cache
def _all_dissections(n: int) -> tuple[tuple[tuple[int, ...], ...], ...]:
    """The dissections of an n-gon (a few hundred for n = 8), fewest parts first."""
    found = {tuple(sorted(d)) for d in _dissections(tuple(range(n)))}
    return tuple(sorted(found, key=len))


def _part_quality(points: np.ndarray) -> float:
    """area / perimeter^2 of a part (0.048 for an equilateral triangle, 0.0625 for a square, ~0 for a sliver),
    or -1 if the part cannot be simulated once stored in float32 around its centroid."""
    try:
        _, _, centroid = polygon_mass_properties(points, 1.0)
        validate_polygon((points - centroid).astype(np.float32).astype(np.float64))
    except GeometryError:
        return -1.0
    area = signed_area(points)  # > 0: parts are counter-clockwise
    perimeter = float(np.sum(np.linalg.norm(points - np.roll(points, -1, axis=0), axis=1)))
    return area / perimeter**2


def cut(vertices, path: str = "polygon") -> list[tuple[int, ...]]:
    """The parts (vertex-index tuples, counter-clockwise) to cut a convex polygon of 5-8 vertices into: the
    fewest parts, and among those the cut whose worst part is least thin (slivers make stiff, jittery welds).
    The largest part comes first. LevelError if no cut gives parts float32 physics can simulate."""
    v = np.asarray(vertices, np.float64)
    quality: dict[tuple[int, ...], float] = {}

    def score(parts) -> float:
        for part in parts:
            if part not in quality:
                quality[part] = _part_quality(v[list(part)])
        return min(quality[p] for p in parts)

    best, best_score = None, 0.0
    for parts in _all_dissections(len(v)):
        if best is not None and len(parts) > len(best):
            break  # sorted by part count: a valid cut with fewer parts always wins
        s = score(parts)
        if s > best_score:
            best, best_score = parts, s
    if best is None:
        raise LevelError(f"{path}: its {len(v)} vertices cannot be cut into triangles and quadrilaterals that "
                         "float32 physics can simulate (some of its vertices are nearly in a line)")
    return sorted(best, key=lambda part: -signed_area(v[list(part)]))


# ---------------------------------------------------------------- a level


def _rotation(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def _distance_to(point: np.ndarray, part: np.ndarray) -> float:
    """Distance from a point to a convex counter-clockwise polygon (0 inside or on it)."""
    edges = np.roll(part, -1, axis=0) - part
    rel = point - part
    if np.all(edges[:, 0] * rel[:, 1] - edges[:, 1] * rel[:, 0] >= 0):
        return 0.0
    t = np.clip(np.sum(rel * edges, axis=1) / np.sum(edges * edges, axis=1), 0.0, 1.0)
    return float(np.min(np.linalg.norm(rel - t[:, None] * edges, axis=1)))


def _inverse_inertia(body: BodySpec) -> float:
    if body.fixed:
        return 0.0
    if body.shape == "circle":
        return 1.0 / circle_mass_properties(body.radius, body.density)[1]
    return 1.0 / polygon_mass_properties(body.vertices, body.density)[1]


@dataclasses.dataclass
class _Parts:
    indices: list[int]  # body index of each part
    centroids: list[np.ndarray]  # in the polygon's body frame
    outlines: list[np.ndarray]  # part vertices in the polygon's body frame

    def holding(self, anchor) -> int:
        """Which part a joint or thruster anchored at `anchor` (polygon body frame) goes on: the one under it (the
        largest on a seam), or for an anchor outside the polygon the largest part, which carries loads with the
        least strain on the welds."""
        point = np.asarray(anchor, np.float64)
        distances = [_distance_to(point, outline) for outline in self.outlines]
        inside = [k for k, d in enumerate(distances) if d == 0.0]
        return inside[0] if inside else 0


def split_polygons(spec: LevelSpec) -> Split:
    """The level with every polygon of more than MAX_PART_VERTICES vertices replaced by welded parts (see the
    module docstring). Bodies keep their indices; the extra parts are appended after the last body, welds after
    the last joint. The spec's polygons must be valid (as `describe` gives them)."""
    bodies = list(spec.bodies)
    joints = [dataclasses.replace(j) for j in spec.joints]
    thrusters = [dataclasses.replace(t) for t in spec.thrusters]
    jointed = {j.a for j in spec.joints} | {j.b for j in spec.joints}
    parts_of: dict[int, _Parts] = {}
    polygons: list[SplitPolygon] = []
    welds: list[JointSpec] = []

    for i, body in enumerate(spec.bodies):
        if body.shape != "polygon" or len(body.vertices) <= MAX_PART_VERTICES:
            continue
        v = np.asarray(body.vertices, np.float64)
        cuts = cut(v, body.path)
        rotation = _rotation(body.angle)
        parts = _Parts([], [], [])
        for k, corners in enumerate(cuts):
            outline = v[list(corners)]
            centroid = polygon_mass_properties(outline, 1.0)[2]
            offset = rotation @ centroid  # world-frame offset of the part's centroid from the polygon's
            part = dataclasses.replace(
                body,
                path=body.path if k == 0 else f"{body.path} (part {k + 1} of its split)",
                position=tuple(np.asarray(body.position, np.float64) + offset),
                vertices=(outline - centroid).tolist(),
                # The velocity of that point of the rotating polygon: v + w x r.
                velocity=(body.velocity[0] - body.angular_velocity * offset[1],
                          body.velocity[1] + body.angular_velocity * offset[0]),
            )
            if k == 0:
                bodies[i] = part
                parts.indices.append(i)
            else:
                parts.indices.append(len(bodies))
                bodies.append(part)
            parts.centroids.append(centroid)
            parts.outlines.append(outline)
        parts_of[i] = parts

        added = 0
        if not body.fixed or i in jointed:
            for p, q, midpoint in _weld_tree(cuts, v):
                welds.append(JointSpec(
                    path=f"{body.path} (weld {added + 1} of its split)",
                    a=parts.indices[p], b=parts.indices[q],
                    anchor_a=tuple(midpoint - parts.centroids[p]), anchor_b=tuple(midpoint - parts.centroids[q]),
                    ref_angle=0.0, fixed=True,
                ))
                added += 1
        polygons.append(SplitPolygon(i, body.path, len(v), tuple(parts.indices), added))

    for joint in joints:
        for side in ("a", "b"):
            body = getattr(joint, side)
            if body in parts_of:
                parts = parts_of[body]
                anchor = getattr(joint, f"anchor_{side}")
                k = parts.holding(anchor)
                setattr(joint, side, parts.indices[k])
                setattr(joint, f"anchor_{side}", tuple(np.asarray(anchor, np.float64) - parts.centroids[k]))
    for thruster in thrusters:
        if thruster.body in parts_of:
            parts = parts_of[thruster.body]
            k = parts.holding(thruster.anchor)
            thruster.body = parts.indices[k]
            thruster.anchor = tuple(np.asarray(thruster.anchor, np.float64) - parts.centroids[k])

    motor_scale = _keep_motor_strength(spec, bodies, joints, parts_of)
    out = dataclasses.replace(spec, bodies=bodies, joints=joints + welds, thrusters=thrusters)
    return Split(out, polygons, motor_scale)


def _weld_tree(cuts: list[tuple[int, ...]], v: np.ndarray) -> list[tuple[int, int, np.ndarray]]:
    """(part, part, midpoint of their shared diagonal) linking every part to the first (a tree: parts of a
    dissection share diagonals as the edges of a tree)."""
    linked, edges = {0}, []
    while len(linked) < len(cuts):
        for p, q in itertools.product(sorted(linked), range(len(cuts))):
            shared = set(cuts[p]) & set(cuts[q])
            if q not in linked and len(shared) == 2:
                a, b = sorted(shared)
                edges.append((p, q, (v[a] + v[b]) / 2))
                linked.add(q)
                break
    return edges


def _keep_motor_strength(spec: LevelSpec, bodies: list[BodySpec], joints: list[JointSpec],
                         parts_of: dict[int, _Parts]) -> dict[int, float]:
    """Scale the power of revolute joints moved onto parts so their motor keeps its torque limit (see the module
    docstring); returns joint index -> factor for those changed."""
    scale = {}
    for k, (before, after) in enumerate(zip(spec.joints, joints, strict=False)):
        if before.fixed or (before.a not in parts_of and before.b not in parts_of):
            continue
        old = _inverse_inertia(spec.bodies[before.a]) + _inverse_inertia(spec.bodies[before.b])
        new = _inverse_inertia(bodies[after.a]) + _inverse_inertia(bodies[after.b])
        if old == 0 or new == old:
            continue
        factor = new / old
        power = before.motor_power * factor
        high = ranges.RANGES["joint.motor.power"].high
        if power > high:
            raise LevelError(f"{before.path}: its motor would need power {power:.4g} (> {high:g}) to keep its "
                             "strength on the part of the split polygon it drives; lower its power")
        after.motor_power = power
        scale[k] = factor
    return scale
