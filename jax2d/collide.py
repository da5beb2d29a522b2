"""Narrow phase: contact manifolds for one pair of shapes (the caller vmaps over pair lists).

Every function takes world-frame poses and returns a `Manifold` of two points with
fixed shapes; points that do not exist are masked out with `valid`, so the code
has no data-dependent control flow and runs unchanged under `jit` / `vmap`.
Outputs are always finite: divisions are guarded, padded polygon vertices are
replaced before use, and undefined directions fall back to (0, 1).

Algorithms (the standard published ones):

- Polygon vs polygon (separating axis theorem + reference-face clipping, as in
  Ericson, "Real-Time Collision Detection", and Catto's GDC talks). For every
  real edge of each polygon the separation is the smallest signed distance of
  the other polygon's vertices to that edge's line; the largest such value over
  both polygons is the separating-axis estimate. The face achieving it is the
  reference face; polygon A is preferred unless B beats it by a small tolerance,
  so the choice does not flicker between frames. The incident edge is the other
  polygon's edge whose normal is most anti-parallel to the reference normal. The
  incident segment is clipped to the slab between the reference face's two side
  planes (Sutherland-Hodgman on a segment), leaving up to two points whose
  separation is their signed distance to the reference face. Each contact point is
  the midpoint between the incident point and its projection on the face. The work
  is done in A's body frame for precision at large world coordinates.
- Polygon vs circle. The circle centre is moved into the polygon frame. Outside
  the polygon, the closest point on the boundary (over all real edges) gives the
  distance and the normal (a face normal in a face region, the centre direction in
  a vertex region). Inside, the face of largest separation (the least negative
  signed distance) gives both. separation = signed distance to the polygon minus
  the radius.
- Circle vs circle: separation = centre distance minus the radii, normal along the
  centre line.

Feature keys (used to match points between steps for warm starting; -1 for points
that are not valid):
- polygon-polygon: ((flip * 8 + reference edge) * 8 + incident edge) * 2 + clip end,
  flip = 1 when the reference face belongs to B;
- polygon-circle: the polygon edge index for a face region or inside, 8 + vertex
  index for a vertex region;
- circle-circle: 0.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

LINEAR_SLOP = 0.005  # m; only used to size the reference-face hysteresis below
FLIP_TOLERANCE = 0.1 * LINEAR_SLOP  # B's face must beat A's by this much to become the reference
_TINY = 1e-12  # squared lengths below this count as zero
_DEGENERATE_EDGE = 1e-6  # m; shorter edges cannot be reference or incident faces
_BIG = 1e9  # finite stand-in for +-infinity inside masked min / max (never returned)
MAX_VERTICES = 8  # keys and vertex ids assume at most this many vertices


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Manifold:
    """Up to two contact points between shapes A and B."""

    normal: jax.Array  # (2,) unit vector, world frame, from A towards B
    point: jax.Array  # (2, 2) world contact points, midway between the surfaces
    separation: jax.Array  # (2,) signed gap along the normal; negative = overlap
    key: jax.Array  # (2,) int32 feature key (see module docstring); -1 when not valid
    valid: jax.Array  # (2,) bool: the point exists and separation < speculative distance


def _rotate(angle, v):
    """Rotate vectors v (..., 2) counter-clockwise by `angle`."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    x, y = v[..., 0], v[..., 1]
    return jnp.stack([c * x - s * y, s * x + c * y], axis=-1)


def _unrotate(angle, v):
    """Rotate vectors v (..., 2) clockwise by `angle` (world -> body orientation)."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    x, y = v[..., 0], v[..., 1]
    return jnp.stack([c * x + s * y, -s * x + c * y], axis=-1)


def _normalize(v, fallback):
    """v / |v|, or `fallback` where |v| is (nearly) zero. Gradient-safe (no 0/0 in either branch)."""
    len2 = jnp.sum(v * v, axis=-1, keepdims=True)
    ok = len2 > _TINY
    unit = v / jnp.sqrt(jnp.where(ok, len2, 1.0))
    return jnp.where(ok, unit, jnp.asarray(fallback, v.dtype))


def _safe_sqrt(x):
    return jnp.sqrt(jnp.maximum(x, _TINY)) * (x > _TINY)


def _f32(x):
    return jnp.asarray(x, jnp.float32)


class _Edges:
    """Real edges of a padded counter-clockwise polygon, as (V,) / (V, 2) arrays."""

    def __init__(self, verts, n):
        num = verts.shape[0]
        n = jnp.clip(jnp.asarray(n, jnp.int32), 1, num)
        index = jnp.arange(num)
        self.real = index < n
        # Padding may hold anything (even NaN): replace it by vertex 0 before any arithmetic.
        self.v1 = jnp.where(self.real[:, None], verts, verts[0])
        self.next = jnp.where(index + 1 < n, index + 1, 0)
        self.v2 = self.v1[self.next]
        edge = self.v2 - self.v1
        # Outward normal of a counter-clockwise edge is the edge rotated by -90 degrees.
        self.normal = _normalize(jnp.stack([edge[:, 1], -edge[:, 0]], axis=-1), (0.0, 1.0))
        self.face = self.real & (jnp.sum(edge * edge, axis=-1) > _DEGENERATE_EDGE**2)


def _pad_vertices(verts, size):
    extra = size - verts.shape[0]
    return verts if extra == 0 else jnp.pad(verts, ((0, extra), (0, 0)))


def _max_face_separation(faces: _Edges, points: _Edges):
    """Best separating face of `faces` against the real vertices of `points`: (index, separation)."""
    # d[i, j] = signed distance of point j to the line of face i
    d = jnp.einsum("ik,ijk->ij", faces.normal, points.v1[None, :, :] - faces.v1[:, None, :])
    per_face = jnp.min(jnp.where(points.real[None, :], d, _BIG), axis=1)
    per_face = jnp.where(faces.face, per_face, -_BIG)
    index = jnp.argmax(per_face)
    return index, per_face[index]


def _clip_segment(p1, p2, d1, d2):
    """Keep the part of segment p1-p2 where the signed distance d <= 0. Returns (p1, p2, non-empty)."""
    denom = d1 - d2
    frac = jnp.where(jnp.abs(denom) > _TINY, d1 / jnp.where(jnp.abs(denom) > _TINY, denom, 1.0), 0.0)
    cross = p1 + jnp.clip(frac, 0.0, 1.0) * (p2 - p1)
    new_p1 = jnp.where(d1 > 0.0, cross, p1)
    new_p2 = jnp.where(d2 > 0.0, cross, p2)
    return new_p1, new_p2, (d1 <= 0.0) | (d2 <= 0.0)


def collide_polygons(pos_a, angle_a, verts_a, n_a, pos_b, angle_b, verts_b, n_b, speculative_distance) -> Manifold:
    """Contact manifold between two convex polygons (SAT + reference-face clipping)."""
    pos_a, angle_a, pos_b, angle_b = _f32(pos_a), _f32(angle_a), _f32(pos_b), _f32(angle_b)
    verts_a, verts_b = _f32(verts_a), _f32(verts_b)
    spec = _f32(speculative_distance)
    size = max(verts_a.shape[0], verts_b.shape[0])
    verts_a, verts_b = _pad_vertices(verts_a, size), _pad_vertices(verts_b, size)

    # Work in A's body frame: B's vertices are expressed relative to A's centre.
    a = _Edges(verts_a, n_a)
    offset = _unrotate(angle_a, pos_b - pos_a)
    b_in_a = _rotate(angle_b - angle_a, verts_b) + offset
    b = _Edges(b_in_a, n_b)

    edge_a, sep_a = _max_face_separation(a, b)
    edge_b, sep_b = _max_face_separation(b, a)
    flip = sep_b > sep_a + FLIP_TOLERANCE

    def pick(field):
        return jnp.where(flip, getattr(b, field), getattr(a, field))

    ref_v1, ref_v2, ref_normal = pick("v1"), pick("v2"), pick("normal")
    inc_v1, inc_v2, inc_normal, inc_face = (
        jnp.where(flip, getattr(a, f), getattr(b, f)) for f in ("v1", "v2", "normal", "face")
    )
    ref_edge = jnp.where(flip, edge_b, edge_a)
    n = ref_normal[ref_edge]
    r1, r2 = ref_v1[ref_edge], ref_v2[ref_edge]

    inc_edge = jnp.argmin(jnp.where(inc_face, inc_normal @ n, _BIG))
    p1, p2 = inc_v1[inc_edge], inc_v2[inc_edge]

    # Side planes of the reference face: the tangent t runs from r1 to r2.
    t = jnp.stack([-n[1], n[0]])
    p1, p2, ok1 = _clip_segment(p1, p2, -jnp.dot(p1 - r1, t), -jnp.dot(p2 - r1, t))
    p1, p2, ok2 = _clip_segment(p1, p2, jnp.dot(p1 - r2, t), jnp.dot(p2 - r2, t))
    incident = jnp.stack([p1, p2])  # (2, 2)

    separation = (incident - r1) @ n
    valid = ok1 & ok2 & (separation < spec)
    local_point = incident - 0.5 * separation[:, None] * n
    point = pos_a + _rotate(angle_a, local_point)
    normal = _rotate(angle_a, jnp.where(flip, -n, n))

    key = ((flip.astype(jnp.int32) * MAX_VERTICES + ref_edge) * MAX_VERTICES + inc_edge) * 2 + jnp.arange(2)
    return Manifold(
        normal=normal,
        point=point,
        separation=jnp.where(valid, separation, spec),
        key=jnp.where(valid, key, -1).astype(jnp.int32),
        valid=valid,
    )


def collide_polygon_circle(pos_p, angle_p, verts, n, pos_c, radius, speculative_distance) -> Manifold:
    """Contact between a convex polygon (A) and a circle (B); only point 0 can be valid."""
    pos_p, angle_p, pos_c = _f32(pos_p), _f32(angle_p), _f32(pos_c)
    radius, spec = _f32(radius), _f32(speculative_distance)
    poly = _Edges(_f32(verts), n)
    centre = _unrotate(angle_p, pos_c - pos_p)

    # Face of largest separation: decides inside vs outside and gives the normal inside.
    face_sep = jnp.where(poly.face, jnp.sum(poly.normal * (centre - poly.v1), axis=-1), -_BIG)
    face = jnp.argmax(face_sep)
    outside = face_sep[face] > 0.0

    # Closest point on the boundary, over every real edge (exact for any convex polygon).
    edge = poly.v2 - poly.v1
    len2 = jnp.sum(edge * edge, axis=-1)
    u = jnp.clip(jnp.sum((centre - poly.v1) * edge, axis=-1) / jnp.maximum(len2, _TINY), 0.0, 1.0)
    closest = poly.v1 + u[:, None] * edge
    dist2 = jnp.where(poly.real, jnp.sum((centre - closest) ** 2, axis=-1), _BIG)
    nearest = jnp.argmin(dist2)
    dist = _safe_sqrt(dist2[nearest])
    outward = _normalize(centre - closest[nearest], poly.normal[face])

    local_normal = jnp.where(outside, outward, poly.normal[face])
    gap = jnp.where(outside, dist, face_sep[face])
    separation = gap - radius
    normal = _rotate(angle_p, local_normal)
    point = pos_c - normal * (radius + 0.5 * separation)

    u_near = u[nearest]
    vertex = jnp.where(u_near >= 1.0, poly.next[nearest], nearest)
    in_vertex_region = outside & ((u_near <= 0.0) | (u_near >= 1.0))
    feature = jnp.where(in_vertex_region, MAX_VERTICES + vertex, jnp.where(outside, nearest, face))
    return _single_point(normal, point, separation, feature, spec)


def collide_circles(pos_a, radius_a, pos_b, radius_b, speculative_distance) -> Manifold:
    """Contact between two circles; only point 0 can be valid."""
    pos_a, pos_b = _f32(pos_a), _f32(pos_b)
    radius_a, radius_b, spec = _f32(radius_a), _f32(radius_b), _f32(speculative_distance)
    delta = pos_b - pos_a
    dist = _safe_sqrt(jnp.sum(delta * delta))
    normal = _normalize(delta, (0.0, 1.0))
    separation = dist - radius_a - radius_b
    # Midway between A's surface (pos_a + r_a n) and B's surface (pos_b - r_b n).
    point = 0.5 * (pos_a + pos_b + (radius_a - radius_b) * normal)
    return _single_point(normal, point, separation, 0, spec)


def _single_point(normal, point, separation, feature, spec) -> Manifold:
    """Manifold whose point 0 is the given contact and point 1 is absent."""
    valid0 = separation < spec
    valid = jnp.stack([valid0, jnp.asarray(False)])
    return Manifold(
        normal=normal,
        point=jnp.stack([point, point]),
        separation=jnp.stack([jnp.where(valid0, separation, spec), spec]),
        key=jnp.stack([jnp.where(valid0, feature, -1), -1]).astype(jnp.int32),
        valid=valid,
    )
