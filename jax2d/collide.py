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

from jax2d.math2d import picked, rotation

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


def _f32(x):
    return jnp.asarray(x, jnp.float32)


def _select(index, *values) -> tuple[jax.Array, ...]:
    """Each of `values` at `index`, as one one-hot sum (math2d.picked): under vmap a select beats a gather on the
    CPU."""
    return picked(jnp.arange(values[0].shape[-1]) == index, -1, *values)


def _best(values, largest: bool) -> tuple[jax.Array, jax.Array]:
    """(index, value) of the first largest (or smallest) entry of `values` along its first axis: jnp.argmax and
    jnp.max (argmin and min), a NaN winning as there, as two plain reductions. Under vmap, XLA's CPU backend
    compiles an argmax as a variadic reduce in scalar code (5 of them were 11 % of the step at l, batch 256)."""
    best = jnp.max(values, axis=0) if largest else jnp.min(values, axis=0)
    index = jnp.arange(values.shape[0]).reshape((-1,) + (1,) * (values.ndim - 1))
    first = jnp.where((values == best[None]) | jnp.isnan(values), index, values.shape[0])
    return jnp.min(first, axis=0).astype(jnp.int32), best


class _Polygon:
    """Real edges of a padded counter-clockwise polygon as separate x / y arrays of shape (V,)."""

    def __init__(self, vx, vy, n):
        size = vx.shape[0]
        index = jnp.arange(size)
        n = jnp.clip(jnp.asarray(n, jnp.int32), 1, size)
        self.real = index < n
        # Padding may hold anything (even NaN): replace it by vertex 0 before any arithmetic.
        self.x1 = jnp.where(self.real, vx, vx[0])
        self.y1 = jnp.where(self.real, vy, vy[0])
        last = index == n - 1
        self.x2 = jnp.where(last, self.x1[0], jnp.roll(self.x1, -1))
        self.y2 = jnp.where(last, self.y1[0], jnp.roll(self.y1, -1))
        self.next = jnp.where(last, 0, index + 1)
        ex, ey = self.x2 - self.x1, self.y2 - self.y1
        len2 = ex * ex + ey * ey
        ok = len2 > _TINY
        inv = jnp.where(ok, 1.0 / jnp.sqrt(jnp.where(ok, len2, 1.0)), 0.0)
        # Outward normal of a counter-clockwise edge is the edge rotated by -90 degrees.
        self.nx = jnp.where(ok, ey * inv, 0.0)
        self.ny = jnp.where(ok, -ex * inv, 1.0)
        self.face = self.real & (len2 > _DEGENERATE_EDGE**2)

    def pick(self, other: _Polygon, flip):
        """Elementwise choice between two polygons' edge arrays."""
        out = object.__new__(_Polygon)
        for f in ("x1", "y1", "x2", "y2", "nx", "ny", "face", "real"):
            setattr(out, f, jnp.where(flip, getattr(other, f), getattr(self, f)))
        return out


def _max_face_separation(faces: _Polygon, points: _Polygon):
    """Best separating face of `faces` against the real vertices of `points`: (index, separation)."""
    # d[i, j] = signed distance of point j to the line of face i
    d = faces.nx[:, None] * (points.x1[None, :] - faces.x1[:, None]) \
        + faces.ny[:, None] * (points.y1[None, :] - faces.y1[:, None])
    per_face = jnp.min(jnp.where(points.real[None, :], d, _BIG), axis=1)
    per_face = jnp.where(faces.face, per_face, -_BIG)
    return _best(per_face, True)


def _clip(p1, p2, d1, d2):
    """Keep the part of segment p1-p2 (tuples of x, y) where the signed distance d <= 0."""
    denom = d1 - d2
    usable = jnp.abs(denom) > _TINY
    frac = jnp.clip(jnp.where(usable, d1 / jnp.where(usable, denom, 1.0), 0.0), 0.0, 1.0)
    cx, cy = p1[0] + frac * (p2[0] - p1[0]), p1[1] + frac * (p2[1] - p1[1])
    q1 = (jnp.where(d1 > 0.0, cx, p1[0]), jnp.where(d1 > 0.0, cy, p1[1]))
    q2 = (jnp.where(d2 > 0.0, cx, p2[0]), jnp.where(d2 > 0.0, cy, p2[1]))
    return q1, q2, (d1 <= 0.0) | (d2 <= 0.0)


def _pad_vertices(verts, size):
    extra = size - verts.shape[0]
    return verts if extra == 0 else jnp.pad(verts, ((0, extra), (0, 0)))


def _to_world(c, s, pos, x, y):
    return pos[0] + c * x - s * y, pos[1] + s * x + c * y


def collide_polygons(pos_a, angle_a, verts_a, n_a, pos_b, angle_b, verts_b, n_b, speculative_distance) -> Manifold:
    """Contact manifold between two convex polygons (SAT + reference-face clipping)."""
    angle_a, angle_b = _f32(angle_a), _f32(angle_b)
    return collide_polygons_rotated(pos_a, rotation(angle_a), verts_a, n_a, pos_b, rotation(angle_b - angle_a),
                                    verts_b, n_b, speculative_distance)


def collide_polygons_rotated(pos_a, rot_a, verts_a, n_a, pos_b, rot_ba, verts_b, n_b,
                             speculative_distance) -> Manifold:
    """collide_polygons with the rotations given (math2d.rotation): rot_a of angle_a, rot_ba of angle_b - angle_a.
    The narrow phase computes them once per pair: fused into the vertices' transforms, each cosine and sine was
    computed once per vertex and per use."""
    pos_a, pos_b = _f32(pos_a), _f32(pos_b)
    spec = _f32(speculative_distance)
    size = max(verts_a.shape[0], verts_b.shape[0])
    verts_a, verts_b = _pad_vertices(_f32(verts_a), size), _pad_vertices(_f32(verts_b), size)

    # Work in A's body frame for precision far from the origin.
    ca, sa = rot_a[0], rot_a[1]
    dx, dy = pos_b[0] - pos_a[0], pos_b[1] - pos_a[1]
    ox, oy = ca * dx + sa * dy, -sa * dx + ca * dy
    cr, sr = rot_ba[0], rot_ba[1]
    a = _Polygon(verts_a[:, 0], verts_a[:, 1], n_a)
    b = _Polygon(ox + cr * verts_b[:, 0] - sr * verts_b[:, 1], oy + sr * verts_b[:, 0] + cr * verts_b[:, 1], n_b)

    edge_a, sep_a = _max_face_separation(a, b)
    edge_b, sep_b = _max_face_separation(b, a)
    flip = sep_b > sep_a + FLIP_TOLERANCE
    ref, inc = a.pick(b, flip), b.pick(a, flip)
    ref_edge = jnp.where(flip, edge_b, edge_a)
    nx, ny, r1x, r1y, r2x, r2y = _select(ref_edge, ref.nx, ref.ny, ref.x1, ref.y1, ref.x2, ref.y2)
    r1, r2 = (r1x, r1y), (r2x, r2y)

    inc_edge, _ = _best(jnp.where(inc.face, inc.nx * nx + inc.ny * ny, _BIG), False)
    p1x, p1y, p2x, p2y = _select(inc_edge, inc.x1, inc.y1, inc.x2, inc.y2)
    p1, p2 = (p1x, p1y), (p2x, p2y)

    # Side planes of the reference face: the tangent t runs from r1 to r2.
    tx, ty = -ny, nx

    def along(p, r):
        return (p[0] - r[0]) * tx + (p[1] - r[1]) * ty

    p1, p2, ok1 = _clip(p1, p2, -along(p1, r1), -along(p2, r1))
    p1, p2, ok2 = _clip(p1, p2, along(p1, r2), along(p2, r2))
    px, py = jnp.stack([p1[0], p2[0]]), jnp.stack([p1[1], p2[1]])

    separation = (px - r1[0]) * nx + (py - r1[1]) * ny
    valid = ok1 & ok2 & (separation < spec)
    wx, wy = _to_world(ca, sa, pos_a, px - 0.5 * separation * nx, py - 0.5 * separation * ny)
    sign = jnp.where(flip, -1.0, 1.0)
    normal = jnp.stack([sign * (ca * nx - sa * ny), sign * (sa * nx + ca * ny)])

    key = ((flip.astype(jnp.int32) * MAX_VERTICES + ref_edge) * MAX_VERTICES + inc_edge) * 2 + jnp.arange(2)
    return Manifold(
        normal=normal,
        point=jnp.stack([wx, wy], axis=-1),
        separation=jnp.where(valid, separation, spec),
        key=jnp.where(valid, key, -1).astype(jnp.int32),
        valid=valid,
    )


def collide_polygon_circle(pos_p, angle_p, verts, n, pos_c, radius, speculative_distance) -> Manifold:
    """Contact between a convex polygon (A) and a circle (B); only point 0 can be valid."""
    return collide_polygon_circle_rotated(pos_p, rotation(_f32(angle_p)), verts, n, pos_c, radius,
                                          speculative_distance)


def collide_polygon_circle_rotated(pos_p, rot_p, verts, n, pos_c, radius, speculative_distance) -> Manifold:
    """collide_polygon_circle with the polygon's rotation given: rot_p = math2d.rotation(angle_p)."""
    pos_p, pos_c = _f32(pos_p), _f32(pos_c)
    radius, spec = _f32(radius), _f32(speculative_distance)
    verts = _f32(verts)
    poly = _Polygon(verts[:, 0], verts[:, 1], n)
    c, s = rot_p[0], rot_p[1]
    dx, dy = pos_c[0] - pos_p[0], pos_c[1] - pos_p[1]
    cx, cy = c * dx + s * dy, -s * dx + c * dy

    # Face of largest separation: decides inside vs outside and gives the normal inside.
    face_sep = jnp.where(poly.face, poly.nx * (cx - poly.x1) + poly.ny * (cy - poly.y1), -_BIG)
    face, best = _best(face_sep, True)
    outside = best > 0.0

    # Closest point on the boundary, over every real edge (exact for any convex polygon).
    ex, ey = poly.x2 - poly.x1, poly.y2 - poly.y1
    len2 = ex * ex + ey * ey
    u = jnp.clip(((cx - poly.x1) * ex + (cy - poly.y1) * ey) / jnp.maximum(len2, _TINY), 0.0, 1.0)
    qx, qy = poly.x1 + u * ex, poly.y1 + u * ey
    dist2 = jnp.where(poly.real, (cx - qx) ** 2 + (cy - qy) ** 2, _BIG)
    nearest, near2 = _best(dist2, False)
    dist = jnp.sqrt(jnp.maximum(near2, _TINY)) * (near2 > _TINY)
    near_x, near_y, u_near, next_vertex = _select(nearest, qx, qy, u, poly.next.astype(jnp.float32))
    ox, oy = cx - near_x, cy - near_y
    olen2 = ox * ox + oy * oy
    ook = olen2 > _TINY
    oinv = jnp.where(ook, 1.0 / jnp.sqrt(jnp.where(ook, olen2, 1.0)), 0.0)
    fnx, fny = _select(face, poly.nx, poly.ny)
    lnx = jnp.where(outside & ook, ox * oinv, fnx)
    lny = jnp.where(outside & ook, oy * oinv, fny)
    gap = jnp.where(outside, dist, best)
    separation = gap - radius
    normal = jnp.stack([c * lnx - s * lny, s * lnx + c * lny])
    point = pos_c - normal * (radius + 0.5 * separation)

    vertex = jnp.where(u_near >= 1.0, next_vertex.astype(jnp.int32), nearest)
    in_vertex_region = outside & ((u_near <= 0.0) | (u_near >= 1.0))
    feature = jnp.where(in_vertex_region, MAX_VERTICES + vertex, jnp.where(outside, nearest, face))
    return _single_point(normal, point, separation, feature, spec)


def collide_circles(pos_a, radius_a, pos_b, radius_b, speculative_distance) -> Manifold:
    """Contact between two circles; only point 0 can be valid."""
    pos_a, pos_b = _f32(pos_a), _f32(pos_b)
    radius_a, radius_b, spec = _f32(radius_a), _f32(radius_b), _f32(speculative_distance)
    dx, dy = pos_b[0] - pos_a[0], pos_b[1] - pos_a[1]
    len2 = dx * dx + dy * dy
    ok = len2 > _TINY
    inv = jnp.where(ok, 1.0 / jnp.sqrt(jnp.where(ok, len2, 1.0)), 0.0)
    dist = len2 * inv
    normal = jnp.stack([jnp.where(ok, dx * inv, 0.0), jnp.where(ok, dy * inv, 1.0)])
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
