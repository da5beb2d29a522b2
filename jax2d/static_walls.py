"""Continuous collision and walls at the end of a step: nothing gets through a body, nor into a wall (issues 28, 35).

Three position stages run after the joint projection (step.py's _solve), on batch-last arrays, in the order
sweep back, push out, sweep back, centre out. The second sweep back also takes every centre whose path, in a
polygon's frame, went through that polygon, at any speed (_centres_inside's "through"):

    sweep back      continuous collision for a body that moved farther in the step than the speculative
                    margin covered (a light body sent off by a heavy fast one): its core disc (CORE_FRACTION
                    of its inner radius) is swept along its centre's segment against every other polygon
                    (Cyrus-Beck clipping against the edge half-planes grown by the core radius) and circle it
                    collides with, static or dynamic (a moving one in its own frame: the segment from the
                    centre's place relative to it at the step's start to that at the end); where it enters one
                    from outside, the body goes back to that entry point, placed by the other body's end pose,
                    its angle to the same fraction of its turn, keeping its velocity, so the next step's contact
                    resolves the impact (Box2D v3's continuous collision, simplified; Box2D sweeps fast bodies
                    against static ones and "bullets" against dynamic ones: here every fast body is a bullet).
    push out        non-linear Gauss-Seidel position correction of the contact points with one static side:
                    a dynamic body deeper in a static one than PUSH_TOLERANCE linear slops is moved out,
                    along the step's contact normals, to that depth (at most MAX_PUSH per point and sweep). The joint
                    projection solves all joints exactly but ignores contacts, so motors at full power pushed
                    a box 20 cm into a floor in one step (tests/jax2d/accuracy.crowded_walls).
    centre out      a dynamic body whose centre still ends inside a polygon it collides with, static or
                    dynamic, goes out through the face it came in by (in that polygon's frame), with every body
                    its joints connect it to, by one translation (centre_out). A dynamic polygon counts because
                    a light body squeezed by a heavy one into a thin free plank was crushed through it: the
                    contact sweeps move momentum through a light body only about its own mass at a time.
                    Dynamic circles do not count (a circle is never thin), nor do static ones.

Each is skipped, batch-wide (lax.cond), in steps where no scene of the batch needs it.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jax2d import contact_solver
from jax2d.control import if_any
from jax2d.math2d import Pose, Vel, picked, rotation, stored
from jax2d.pairs import ContactLayout
from jax2d.state import Bodies, modes_agree
from jax2d.sweeps import ROW, Block, Rows, pack_rows, sweep, velocity_along

# Continuous collision sweeps a disc of this fraction of a body's inner radius (a circle's radius, a polygon's
# smallest centre-to-edge distance): a body resting on a wall, or overlapping it by a few slops, keeps its core
# well outside the wall, so ordinary contacts never trigger it.
CORE_FRACTION = 0.5
# The push-out leaves overlaps up to this many linear slops alone (the settling target, 2 slops): it
# is for the deep overlaps the joint projection makes, not for resting contact, whose overlap under a heavy
# load the soft contacts settle (a 100 kg box on a 1 kg box: 8.7 mm into the floor). Pushed to the slop, the
# light box went out of the floor while the heavy one did not follow, and their overlap grew from 8.7 to
# 12.4 mm.
PUSH_TOLERANCE = 2.0
# Push-out sweeps per round, rounds per step (a joint projection between two), and the largest correction of
# one point in one sweep (m). Crowded scene 55 of tests/jax2d/test_physics.py (a welded arm that a motor at
# full power swings into a wall), weld gap at the end: 128 mm with one round of 2 sweeps, 17 mm with 3 rounds,
# 6.6 mm with 6 (1 or 2 sweeps each), 4.1 mm with 10.
PUSH_SWEEPS = 1
PUSH_ROUNDS = 10
MAX_PUSH = 0.2
# centre_out leaves a centre this many linear slops outside the face it goes out through.
CENTRE_MARGIN = 0.2
# centre_out's rounds, each True where dynamic polygons count as well as static ones: first out of any polygon,
# then out of static ones only, twice (a corner where two walls overlap), so the walls have the last word. With
# dynamic polygons in every round, crowded scene 245 (actions key 3) ended a step with a welded triangle's
# centre in the floor: a body pushed into the floor and the triangle were each inside the other, and moving
# the triangle's assembly out of that body used up the rounds.
CENTRE_ROUNDS = (True, False, False)
_FAR = 1e9  # the separation given to points that the push-out leaves alone


class Shapes(NamedTuple):
    """What the sweep back needs of the bodies, batch-last (per body (N, *batch), polygons (P, V, 2, *batch))."""

    vertices: jax.Array
    n_vertices: jax.Array
    radius: jax.Array
    collision_mode: jax.Array
    active: jax.Array  # (N, *batch)
    core: jax.Array  # (M, *batch) the swept disc's radius; 0 for static bodies and the padding
    reach: jax.Array  # (M, *batch) how far the speculative margin covered each body's travel (m)
    dynamic: jax.Array  # (M, *batch) active and movable (False for the padding)
    polygon: jax.Array  # (P, *batch) active polygons, static or dynamic: no dynamic centre may end inside one
    group: jax.Array  # (M, *batch) joint groups (narrow_phase.joint_labels): equal for bodies joints link


def shapes(b: Bodies, group, reach, speculative, M: int) -> Shapes:
    """Shapes from batch-last bodies; group: (M, *batch) narrow_phase.joint_labels; reach: (N, *batch)
    narrow_phase.step_reach; speculative: (*batch)."""
    v = b.vertices  # (P, V, 2, *batch)
    f = _faces(v, b.n_vertices)
    # Distance from the centre of mass (the frame's origin) to each edge's line: cross(v, e) / |e| (CCW).
    dist = (f.vx * f.ey - f.vy * f.ex) / f.length
    inner = jnp.concatenate([jnp.min(jnp.where(f.used, dist, jnp.inf), axis=1), b.radius])
    dynamic = b.active & (b.inv_mass > 0)
    pad = [(0, M - b.active.shape[0])] + [(0, 0)] * (b.active.ndim - 1)
    core = jnp.pad(jnp.where(dynamic, CORE_FRACTION * jnp.maximum(inner, 0.0), 0.0), pad)
    P = v.shape[0]
    return Shapes(v, b.n_vertices, b.radius, b.collision_mode, b.active, core, jnp.pad(reach + speculative, pad),
                  jnp.pad(dynamic, pad), b.active[:P], group)


def _used(V: int, n_vertices):
    """(P, V, *batch) which vertex slots hold a vertex."""
    idx = jnp.arange(V).reshape((1, V) + (1,) * (n_vertices.ndim - 1))
    return idx < n_vertices[:, None]


def _next_vertex(v, n_vertices):
    """(P, V, 2, *batch) each vertex's successor, wrapping at the polygon's own vertex count."""
    V = v.shape[1]
    idx = jnp.arange(V).reshape((1, V) + (1,) * (n_vertices.ndim - 1))
    last = (idx == n_vertices[:, None] - 1)[:, :, None]
    return jnp.where(last, v[:, :1], jnp.roll(v, -1, axis=1))


def sweep_back(s: Shapes, pose0: Pose, pose: Pose, fixed: bool = False) -> Pose:
    """Put every fast body that entered another body's grown core back at the entry (module docstring).

    pose0, pose: (M, *batch) the step's start and end poses. Bodies that a chain of joints connects are
    not swept against each other.
    The other body may move too: the fast body's centre is followed in the other's frame, from where it is at
    the step's start (in the other's start pose) to where it is at the end (in its end pose), a straight
    segment there; a static body's two poses are the same.
    """
    fast = _fast(s, pose0, pose)
    return if_any(fixed, fast, lambda: _swept_back(s, pose0, pose, fast), lambda: pose)  # (control.py)


def _fast(s: Shapes, pose0: Pose, pose: Pose):
    """(M, *batch) the bodies the sweep back looks at: only a body that went farther than the margin the narrow
    phase kept its contacts in can have passed a body between two steps' contacts; and one that moved less
    than its core cannot enter past it."""
    dx, dy = pose.x - pose0.x, pose.y - pose0.y
    travel = jnp.sqrt(dx * dx + dy * dy)
    return (s.core > 0.0) & (travel > s.reach) & (travel > s.core)


def _swept_back(s: Shapes, pose0: Pose, pose: Pose, fast, through=None) -> Pose:
    """sweep_back's work, for the bodies in `fast` (the others keep their pose, bitwise), and for the pairs in
    `through` (M, P, *batch): a centre that may have gone through a polygon goes back to where it entered it
    (swept as a disc of radius 0, since a fast body's core may have started inside the grown polygon).

    A body goes back to its entry point relative to the body it entered, placed by that body's end pose (its
    angle to the same fraction of its turn). Going back along its own path instead left a moving body
    behind: a fast free plank, pushed by a thrusting ball, swept back against the ball by 11 cm of its own
    travel, ended behind the ball, which was then through it."""
    P = s.vertices.shape[0]
    N = s.active.shape[0]
    M = pose.x.shape[0]
    mode = jnp.pad(s.collision_mode, [(0, M - N)] + [(0, 0)] * (s.collision_mode.ndim - 1))
    active = jnp.pad(s.active, [(0, M - N)] + [(0, 0)] * (s.active.ndim - 1))
    linked = _linked(s.group)  # includes each body itself
    # (M body, M other, *batch)
    may = modes_agree(mode[:, None], mode[None, :]) & ~linked & active[None, :]
    r = s.core[:, None]
    times, entry_x, entry_y = [], [], []  # per (body, other): the entry fraction (1: none), the entry in the world
    if P:
        (x0, y0), (x1, y1) = _centre_in_frames(pose0, P), _centre_in_frames(pose, P)
        qx, qy = x1 - x0, y1 - y0
        f = _faces(s.vertices, s.n_vertices)  # (P, V, *batch), body frame
        t_in = _entry(f, x0, y0, qx, qy, r, may[:, :P] & fast[:, None])
        if through is not None:
            t_in = jnp.minimum(t_in, _entry(f, x0, y0, qx, qy, 0.0, may[:, :P] & through))
        ex, ey = x0 + t_in * qx, y0 + t_in * qy  # the entry in the polygon's frame
        cos, sin = jnp.cos(pose.a[None, :P]), jnp.sin(pose.a[None, :P])
        times.append(t_in)
        entry_x.append(pose.x[None, :P] + cos * ex - sin * ey)
        entry_y.append(pose.y[None, :P] + sin * ex + cos * ey)
    may = may & fast[:, None]
    C = N - P
    if C:
        R = s.radius[None]
        fx, fy = pose0.x[:, None] - pose0.x[None, P:N], pose0.y[:, None] - pose0.y[None, P:N]
        qx = pose.x[:, None] - pose.x[None, P:N] - fx
        qy = pose.y[:, None] - pose.y[None, P:N] - fy
        a = qx * qx + qy * qy
        bq = 2.0 * (fx * qx + fy * qy)
        cq = fx * fx + fy * fy - (R + r) ** 2
        disc = bq * bq - 4.0 * a * cq
        t_in = (-bq - jnp.sqrt(jnp.maximum(disc, 0.0))) / jnp.maximum(2.0 * a, 1e-12)
        hit = (cq > 0.0) & (disc >= 0.0) & (t_in >= 0.0) & (t_in < 1.0) & may[:, P:N]
        times.append(jnp.where(hit, t_in, 1.0))
        entry_x.append(pose.x[None, P:N] + fx + t_in * qx)
        entry_y.append(pose.y[None, P:N] + fy + t_in * qy)
    if not times:
        return pose
    times = jnp.concatenate(times, axis=1)  # (M, N, *batch)
    t = jnp.min(times, axis=1)
    back = t < 1.0  # (a lerp at t = 1 is not bitwise the end pose: a body's result would depend on its batch)
    first = _first_of(times == t[:, None], axis=1)  # the body it entered first
    x, y = picked(first, 1, jnp.concatenate(entry_x, axis=1), jnp.concatenate(entry_y, axis=1))
    return Pose(jnp.where(back, x, pose.x), jnp.where(back, y, pose.y),
                jnp.where(back, pose0.a + t * (pose.a - pose0.a), pose.a))


def _entry(f: _Faces, x0, y0, qx, qy, r, may):
    """(M, P, *batch) where each centre's segment x0 + t q (in each polygon's frame) first enters the polygon
    grown by r (Cyrus-Beck clipping against the edge half-planes n . x <= offset + r), for a core that starts
    outside it; 1 where it does not, or where `may` is False."""
    nx, ny = f.nx, f.ny
    offset = nx * f.vx + ny * f.vy  # (P, V, *batch): inside is n . x <= offset
    used = f.used[None]  # (1, P, V, *batch)
    grown = r[:, :, None] if jnp.ndim(r) else r
    num = offset[None] + grown - (nx[None] * x0[:, :, None] + ny[None] * y0[:, :, None])
    den = nx[None] * qx[:, :, None] + ny[None] * qy[:, :, None]
    entering, leaving = used & (den < 0.0), used & (den > 0.0)
    ratio = num / jnp.where(den == 0.0, 1.0, den)
    # One reduction each for the two extremes (the latest entry, minus the earliest exit) and the two tests
    # (reductions cost per call: math2d.picked).
    t_in, t_out = jnp.max(jnp.stack([jnp.where(entering, ratio, 0.0), jnp.where(leaving, -ratio, -1.0)]), axis=3)
    t_out = -t_out
    outside = used & (num < 0.0)  # the core starts outside the grown polygon
    outside, parallel_out = jnp.any(jnp.stack([outside, outside & (den == 0.0)]), axis=3)
    hit = outside & ~parallel_out & (t_in <= t_out) & (t_in < 1.0) & may
    return jnp.where(hit, t_in, 1.0)


def push_out(layout: ContactLayout, cc: contact_solver.ContactConstraints, const, impulses, plan, pose: Pose,
             vel: Vel, pose0: Pose, slop, rejoin) -> Pose:
    """Move dynamic bodies out of the static bodies they overlap beyond PUSH_TOLERANCE slops (module docstring).

    cc, const: the step's contact constraints, plain and packed; impulses: the packed impulses (only their
    shape is used); plan: the contact sweeps' schedule; slop: (*batch) SimParams.linear_slop;
    vel: the velocities (the projection's position part reads them; they are not changed: also removing a
    pushed point's velocity into the wall, alternating with the velocity projection, left scene 55's weld
    8.7 mm open against 6.6 mm without, at 6 rounds); rejoin(pose, vel) -> (pose, vel): the joint projection. The
    push-out and the projection's position part alternate (PUSH_ROUNDS push-outs, a projection between two): a
    body welded to an arm that a motor pressed into a wall was pushed out alone and the weld opened by 13 cm;
    rejoined, the arm turns back with it. Only scenes with a point deeper than the tolerance change, so a
    scene's result does not depend on the rest of its batch.
    """
    one_static = ((cc.ma == 0.0) != (cc.mb == 0.0)).astype(jnp.float32)  # (S, *batch)
    with_wall = pack_rows(layout, [one_static, one_static]) > 0.0  # (C, 2, K, *batch)
    live = with_wall & (const[:, ROW["nmass0"]:ROW["nmass0"] + 2] > 0.0)
    token = None if plan.fixed else plan.count  # math2d.stored: a traced count (a constant would be folded away)
    allowed = PUSH_TOLERANCE * slop

    def depth(pose):
        sep = contact_solver.current_separation(layout, cc, pose, pose0, token)
        return jnp.where(live, sep, _FAR)

    def push_colour(vels, lam, points, c: Block, sep: Rows):
        for k in range(2):
            s = sep[k] + velocity_along(c, k, vels, c.nx, c.ny)
            move = jnp.clip(-(s + allowed), 0.0, MAX_PUSH)
            vels = vels + c.push("normal", k) * (c.point("nmass", k) * move)[None]
        return vels, None

    def sweeps(pose, sep):
        for i in range(PUSH_SWEEPS):
            if i:
                sep = depth(pose)
            zero = jnp.zeros_like(pose.x)
            d, _ = sweep(layout, Vel(zero, zero, zero), push_colour, const, impulses, plan, sep)
            pose = Pose(pose.x + d.x, pose.y + d.y, pose.a + d.w)
        return pose

    def run(pose, vel, sep):
        deep = sep < -allowed
        scene = jnp.any(deep, axis=(0, 1, 2))  # (*batch) scenes that have a point to push out

        def only_there(new, old):
            return type(old)(*(jnp.where(scene, n, o) for n, o in zip(new, old, strict=True)))

        def round_(_, pose):
            pose = only_there(rejoin(pose, vel)[0], pose)
            return sweeps(pose, depth(pose))

        # A loop, not unrolled: each round holds a whole joint projection, and ten copies of it doubled
        # the step's compile time (s, m, l: 6.3-7.4 s -> 12.1-14.6 s).
        return jax.lax.fori_loop(0, PUSH_ROUNDS - 1, round_, sweeps(pose, sep))

    sep = depth(pose)
    return if_any(plan.fixed, sep < -allowed, functools.partial(run, pose, vel, sep), lambda: pose)


def sweep_back_then_centre_out(s: Shapes, pose0: Pose, pose: Pose, slop, fixed: bool = False,
                               num_static: int = 0, token=None) -> Pose:
    """sweep_back, then centre_out, in one conditional on whether some scene needs either: the step's last
    stage. On the CPU the branch adds to every call's time, taken or not, through the reductions in it
    (docs/engine.md, "Reductions cost per call"); one conditional for both stages measured the same as one
    each. num_static: SolverConfig.num_static, the leading polygons that are always static; their centres
    are left out of the test for one inside (a quarter of its pairs at l, the test being most of what this
    stage costs a step at batch 1). token: a traced non-negative integer (math2d.stored), None in a fixed
    schedule."""
    if not s.vertices.shape[0]:  # no polygons, so no static polygon to be inside
        return sweep_back(s, pose0, pose, fixed)
    fast = _fast(s, pose0, pose)
    faces = _faces(s.vertices, s.n_vertices)
    num_static = min(num_static, s.vertices.shape[0])
    P = faces.vx.shape[0]
    # The polygons' rotations, computed once each: fused into the test, the cosine and sine were computed once
    # per (body, polygon) pair (env l batch 1: +1.8 % with them stored).
    rot = None if token is None else (stored(token, rotation, pose.a[:P]), stored(token, rotation, pose0.a[:P]))
    inside, through = _centres_inside(s, faces, pose, pose0, skip=num_static, rot=rot)

    def run():
        swept = _swept_back(s, pose0, pose, fast, _with_rows(through, num_static))
        return _moved_out(s, faces, pose0, swept, slop, fixed, CENTRE_ROUNDS)

    return if_any(fixed, jnp.any(fast) | jnp.any(inside | through), run, lambda: pose)


def centre_out(s: Shapes, pose0: Pose, pose: Pose, slop, fixed: bool = False) -> Pose:
    """Move a dynamic body whose centre ended the step strictly inside a polygon it collides with (static,
    or dynamic and not linked to it by joints) out through the face it came in by, to CENTRE_MARGIN slops
    outside it (issue 35's walls criterion, and its thin dynamic bodies).

    The last stage, for what the others leave. In crowded scene 245 (actions key 3) a 16 g triangle welded to
    two heavier bodies that motors at full power spin ends a step with its centre 25 cm deep in the floor: the
    joint projection solves the welds exactly and ignores contacts, the push-out turns so light a body about
    its centre rather than moving it, and the sweep back skips a body whose core starts inside.

    - The face: the one the centre was farthest outside of at the step's start (its way in, in the polygon's
      frame at the start: for a moving polygon, relative to it), else, for a centre that started inside, the
      one it is nearest to now.
    - Only the body whose centre is inside moves, whatever the masses: it is the one that was crushed or
      pushed into the other (speed_up_tunnel in tests/jax2d/accuracy.py: a 0.8 g ball between a 0.9 kg box
      and a 60 g plank).
    - The rounds (CENTRE_ROUNDS): the first out of any polygon, then two out of static ones only, so that a
      body moved out of a dynamic polygon into a wall comes out of the wall again.
    - The move: the centre's depth below that face and the margin, for the body and every dynamic body joined
      to it by a chain of joints, by the same translation, so no joint opens (in an assembly with two such
      bodies, the larger move). Moving the triangle alone opened its welds by 25 cm, and the next steps' joint
      solve closed them with speeds that blew the scene apart.
    - Velocities are kept: the next step's contacts take what points into the wall.
    - A centre in two static polygons (a corner where the floor and a wall overlap) goes out of the deeper one,
      then of the other.

    Each round runs, batch-wide, only in steps where some scene has a centre inside (jax2d/control.py);
    testing for one is what it costs in every step.
    """
    return _moved_out(s, _faces(s.vertices, s.n_vertices), pose0, pose, slop, fixed, CENTRE_ROUNDS)


def _moved_out(s: Shapes, faces: _Faces, pose0: Pose, pose: Pose, slop, fixed: bool,
               rounds: tuple[bool, ...]) -> Pose:
    """centre_out's rounds (CENTRE_ROUNDS): each runs where some centre is inside a polygon that the round
    counts, and the first round with none ends them (fixed: every round runs).

    One loop body for all rounds, the polygons a round counts read from the data: three copies of the round
    made the step's program three times as many reductions, and XLA's CPU runtime pays for each reduction in a
    program on every call, run or not (docs/engine.md, "Reductions cost per call")."""
    dynamic_too = jnp.asarray(rounds)

    def inside_of(r, pose):
        return _centres_inside(s, faces, pose, dynamic_too=dynamic_too[r])[0]

    if fixed:
        return jax.lax.fori_loop(0, len(rounds), lambda r, pose: _move_out(s, faces, pose0, pose, inside_of(r, pose),
                                                                             slop), pose)

    def more(carry):
        r, _, inside = carry
        return (r < len(rounds)) & jnp.any(inside)

    def next_round(carry):
        r, pose, inside = carry
        moved = _move_out(s, faces, pose0, pose, inside, slop)
        return r + 1, moved, inside_of(jnp.minimum(r + 1, len(rounds) - 1), moved)

    return jax.lax.while_loop(more, next_round, (jnp.int32(0), pose, inside_of(0, pose)))[1]


class _Faces(NamedTuple):
    """The polygons' edges in their own frames, (P, V, *batch): start vertex, edge vector, its length (at
    least 1e-9), the outward unit normal of a CCW polygon, and which edges are used. Every stage here takes
    its edge geometry from this one place."""

    vx: jax.Array
    vy: jax.Array
    ex: jax.Array
    ey: jax.Array
    length: jax.Array
    nx: jax.Array
    ny: jax.Array
    used: jax.Array


def _faces(vertices, n_vertices) -> _Faces:
    """_Faces of polygons' vertices (P, V, 2, *batch) and vertex counts (P, *batch)."""
    nxt = _next_vertex(vertices, n_vertices)
    vx, vy = vertices[:, :, 0], vertices[:, :, 1]
    ex, ey = nxt[:, :, 0] - vx, nxt[:, :, 1] - vy
    length = jnp.maximum(jnp.sqrt(ex * ex + ey * ey), 1e-9)
    return _Faces(vx, vy, ex, ey, length, ey / length, -ex / length, _used(vertices.shape[1], n_vertices))


def _centre_in_frames(pose: Pose, P: int, skip: int = 0, rot=None):
    """(M - skip body, P polygon, *batch) each body's centre (from body `skip` on) in each polygon's frame;
    rot: the polygons' math2d.rotation, if computed already."""
    cos, sin = (rotation(pose.a[:P]) if rot is None else rot)[:, None]
    rx, ry = pose.x[skip:, None] - pose.x[None, :P], pose.y[skip:, None] - pose.y[None, :P]
    return cos * rx + sin * ry, -sin * rx + cos * ry


def _outside_by(f: _Faces, x, y):
    """(M, P, V, *batch) how far each centre is right of (outside) each edge of a CCW polygon, times its length."""
    return f.ex[None] * (f.vy[None] - y[:, :, None]) - f.ey[None] * (f.vx[None] - x[:, :, None])


def _centres_inside(s: Shapes, f: _Faces, pose: Pose, pose0: Pose | None = None, dynamic_too: bool = True,
                    skip: int = 0, rot=None):
    """(M - skip, P, *batch) dynamic centres (of the bodies from `skip` on: those before are known static)
    strictly inside a polygon they collide with and are not linked to by joints (for static polygons, as
    tests/jax2d/accuracy._inside_static counts them; dynamic_too=False: only those); with pose0, also
    (M - skip, P, *batch) the centres that may have gone through such a polygon in the step, else None
    (_with_rows puts the skipped rows back). rot: (pose's, pose0's) polygon math2d.rotation, if stored already.

    Through: the centre's segment in the polygon's frame (from where it was relative to the polygon at the
    step's start to where it is at the end) enters one edge's half-plane, leaves another's, and lies wholly
    outside none. That holds for every segment that crosses the polygon and for a few that pass a corner;
    _entry's clipping tells them apart, in the conditional. (Clipping here, in every step, cost env s at
    batch 256 a fifth of its speed: a division per edge, each its own kernel.) A light body that a heavy one
    crushed through a thin free plank within one step, or a body fast relative to a polygon that moved, ends
    outside with nothing inside to see; the speculative margin and the sweep back's speed test both look at
    a body's own speed.
    """
    P, V = f.vx.shape[:2]
    M = pose.x.shape[0]
    rot, rot0 = (None, None) if rot is None else rot
    x, y = _centre_in_frames(pose, P, skip, rot)
    mode = jnp.pad(s.collision_mode, [(0, M - s.collision_mode.shape[0])] + [(0, 0)] * (s.collision_mode.ndim - 1))
    polygon = jnp.where(dynamic_too, s.polygon, s.polygon & ~s.dynamic[:P])
    may = (polygon[None] & s.dynamic[skip:, None] & modes_agree(mode[skip:, None], mode[None, :P])
           & (s.group[skip:, None] != s.group[None, :P]))
    x0, y0 = (None, None) if pose0 is None else _centre_in_frames(pose0, P, skip, rot0)
    inside = may
    entered = left = missed = jnp.zeros_like(may)
    # Edge by edge (jnp.all over the vertex axis, written out): the test runs in every step.
    for k in range(V):
        used = f.used[None, :, k]
        b = _ahead(f, k, x, y)  # > 0: outside the edge at the end
        inside = inside & ((b < 0.0) | ~used)
        if pose0 is not None:
            a = _ahead(f, k, x0, y0)  # and at the start
            entered = entered | (used & (a > 0.0) & (b <= 0.0))
            left = left | (used & (a <= 0.0) & (b > 0.0))
            missed = missed | (used & (a > 0.0) & (b > 0.0))  # wholly outside this edge's half-plane
    if pose0 is None:
        return inside, None
    return inside, may & entered & left & ~missed


def _with_rows(pairs, skip: int):
    """(M, P, *batch) from _centres_inside's (M - skip, P, *batch): the skipped static rows, False, put back."""
    return jnp.pad(pairs, [(skip, 0)] + [(0, 0)] * (pairs.ndim - 1)) if skip else pairs


def _ahead(f: _Faces, k: int, x, y):
    """(M, P, *batch) how far centres (x, y) in the polygons' frames are outside edge k, times its length."""
    return f.ex[None, :, k] * (f.vy[None, :, k] - y) - f.ey[None, :, k] * (f.vx[None, :, k] - x)


def _move_out(s: Shapes, f: _Faces, pose0: Pose, pose: Pose, inside, slop) -> Pose:
    """One round of centre_out: each body (with its assembly) out of the polygon it is deepest in."""
    P, V = f.vx.shape[:2]
    connected = _linked(s.group)  # (M, M, *batch), each body with itself
    hit = inside
    length, nx, ny = f.length[None], f.nx[None], f.ny[None]  # outward normals, polygon frame
    used = f.used[None]
    before = jnp.where(used, _outside_by(f, *_centre_in_frames(pose0, P)) / length, -jnp.inf)  # signed distances
    now = jnp.where(used, _outside_by(f, *_centre_in_frames(pose, P)) / length, -jnp.inf)
    came_in = jnp.max(before, axis=2, keepdims=True) >= 0.0
    choice = jnp.argmax(jnp.where(came_in, before, now), axis=2)[:, :, None]
    face = jnp.arange(V).reshape((1, 1, V) + (1,) * (pose.x.ndim - 1)) == choice
    depth, fnx, fny = picked(face, 2, now, nx, ny)
    depth = -depth  # (M, P, *batch) >= 0 for a centre inside
    lift = jnp.where(hit, depth + CENTRE_MARGIN * slop, 0.0)
    cos, sin = jnp.cos(pose.a[None, :P]), jnp.sin(pose.a[None, :P])
    wx, wy = cos * fnx - sin * fny, sin * fnx + cos * fny  # the face's outward normal in the world
    # Per body, the polygon it is deepest in.
    pick = _first_of(lift == jnp.max(lift, axis=1, keepdims=True), axis=1) & hit
    dx, dy, found = picked(pick, 1, lift * wx, lift * wy, 1.0)  # (M, *batch); found: 1 where pick has one
    # Per body, the largest move among the bodies of its assembly (connected), applied to the dynamic ones.
    size = jnp.where(found > 0.0, dx * dx + dy * dy, -1.0)
    lead = jnp.where(connected, size[:, None], -2.0)  # (M member, M body, *batch)
    chosen = _first_of((lead == jnp.max(lead, axis=0, keepdims=True)) & (lead >= 0.0), axis=0)
    gx, gy, any_chosen = picked(chosen, 0, dx[:, None], dy[:, None], 1.0)
    moved = (any_chosen > 0.0) & s.dynamic
    return Pose(jnp.where(moved, pose.x + gx, pose.x), jnp.where(moved, pose.y + gy, pose.y), pose.a)


def _linked(group):
    """(M, M, *batch) bodies that a chain of joints links, each body with itself, from their joint groups."""
    return group[:, None] == group[None, :]


def _first_of(mask, axis: int):
    """mask with only its first true element along `axis` kept."""
    return mask & (jnp.cumsum(mask, axis=axis) == 1)
