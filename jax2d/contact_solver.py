"""Contact constraints: prepare, warm start, solve / relax, store (restitution: restitution.py).

The stages follow Box2D v3's soft step (Catto, "Solver2D", 2024). Contacts are
prepared once per step from the narrow phase. Each substep then warm starts,
solves with a soft position bias, integrates positions and relaxes without the
bias; restitution runs once at the end (restitution.py, on these sweeps).

Slots are solved colour by colour (see pairs.py): within a colour no body
appears twice, so a colour is one vectorised update and the sweep is an exact
Gauss-Seidel pass. Colours without any point are skipped (see schedule).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jax2d.math2d import (
    Pose,
    Softness,
    Vel,
    at,
    cross,
    gather_scene_rows,
    rotate,
    safe_inverse,
    scene_rows,
    set_at,
    stored,
    take_rows,
)
from jax2d.pairs import ContactLayout


class ContactConstraints(NamedTuple):
    """Per slot (S,) or per slot and point (S, 2) constraint data for one step."""

    nx: jax.Array  # (S,)
    ny: jax.Array
    friction: jax.Array  # (S,)
    restitution: jax.Array  # (S,)
    ma: jax.Array  # (S,) inverse masses and inertias of the two bodies
    ia: jax.Array
    mb: jax.Array
    ib: jax.Array
    rax: jax.Array  # (S, 2) anchors from the centres of mass, world orientation
    ray: jax.Array
    rbx: jax.Array
    rby: jax.Array
    base_separation: jax.Array  # (S, 2) separation minus n.(rb - ra) at the step start
    normal_mass: jax.Array  # (S, 2) 0 for points that do not exist
    tangent_mass: jax.Array  # (S, 2)
    relative_velocity: jax.Array  # (S, 2) normal velocity before solving, for restitution
    impact_boost: jax.Array  # (S, 2) approach speed gained under gravity before impact (<= 0), for restitution
    normal_gravity: jax.Array  # (S,) gravity's relative normal acceleration g_n (normal_gravity), for restitution


class ContactImpulses(NamedTuple):
    normal: jax.Array  # (S, 2)
    tangent: jax.Array  # (S, 2)
    max_normal: jax.Array  # (S, 2) largest normal impulse applied this step


def prepare(layout: ContactLayout, manifold, valid, pose: Pose, vel: Vel, inv_mass, inv_inertia,
            friction, restitution, gravity, h) -> ContactConstraints:
    """Build constraints from the step's manifolds (one row per slot), on batch-last arrays:
    per body (M, *batch), manifold fields with the batch after their own axes; gravity (2, *batch);
    h: the substep."""
    a, b = layout.slot_a, layout.slot_b  # (S,), or (S, B): each scene's own pairs (broad_phase)
    ta = functools.partial(take_rows, idx=a)
    tb = functools.partial(take_rows, idx=b)
    nx, ny = manifold.normal[:, 0], manifold.normal[:, 1]
    px, py = manifold.point[:, :, 0], manifold.point[:, :, 1]
    rax, ray = px - ta(pose.x)[:, None], py - ta(pose.y)[:, None]
    rbx, rby = px - tb(pose.x)[:, None], py - tb(pose.y)[:, None]
    ma, ia, mb, ib = ta(inv_mass), ta(inv_inertia), tb(inv_mass), tb(inv_inertia)
    n_x, n_y = nx[:, None], ny[:, None]
    base = manifold.separation - ((rbx - rax) * n_x + (rby - ray) * n_y)

    def effective_mass(dx, dy):
        rna, rnb = cross(rax, ray, dx, dy), cross(rbx, rby, dx, dy)
        k = (ma + mb)[:, None] + ia[:, None] * rna**2 + ib[:, None] * rnb**2
        return jnp.where(valid, safe_inverse(k), 0.0)

    dvx, dvy = _relative_velocity(ta(vel.x)[:, None], ta(vel.y)[:, None], ta(vel.w)[:, None],
                                  tb(vel.x)[:, None], tb(vel.y)[:, None], tb(vel.w)[:, None], rax, ray, rbx, rby)
    rel = dvx * n_x + dvy * n_y
    acc = normal_gravity(nx, ny, ma, mb, gravity)
    return ContactConstraints(
        nx=nx, ny=ny,
        friction=jnp.sqrt(ta(friction) * tb(friction)),
        restitution=jnp.maximum(ta(restitution), tb(restitution)),
        ma=ma, ia=ia, mb=mb, ib=ib,
        rax=rax, ray=ray, rbx=rbx, rby=rby,
        base_separation=base,
        normal_mass=effective_mass(n_x, n_y),
        tangent_mass=effective_mass(n_y, -n_x),
        relative_velocity=rel,
        impact_boost=_impact_boost(rel, manifold.separation, acc[:, None], h),
        normal_gravity=acc,
    )


def normal_gravity(nx, ny, ma, mb, gravity):
    """(S, *batch) gravity's relative normal acceleration of a contact's b side against its a side (a static
    side does not fall). nx, ny, ma, mb (inverse masses): (S, *batch); gravity: (2, *batch)."""
    falls = lambda m: (m > 0.0).astype(jnp.float32)  # noqa: E731
    return (falls(mb) - falls(ma)) * (gravity[0] * nx + gravity[1] * ny)


def _impact_boost(rel, separation, acc, h):
    """How much faster a point approaches when it hits than its stored normal velocity rel says: with the
    relative normal acceleration acc from gravity, the approach speed at impact is sqrt(v^2 - 2 acc s) (free
    flight over the gap s), where v = rel + acc h / 2 is the approach velocity at the step's start: the
    substeps integrate velocity before position (symplectic Euler), so a stored velocity is the mean over the
    last substep, half a substep behind. Restitution bounces at e times this speed, not e times rel, which
    left a ball dropped on the floor 1-2 % low per bounce, and 15 % low on small bounces at dt = 1/60 (the
    step-start speed misses g t of the fall)."""
    v = rel + acc * (0.5 * h)
    gap = jnp.maximum(separation, 0.0)
    impact = -jnp.sqrt(jnp.maximum(v * v - 2.0 * acc * gap, 0.0))
    return jnp.where(v < 0.0, impact - rel, 0.0)


def _relative_velocity(vax, vay, wa, vbx, vby, wb, rax, ray, rbx, rby):
    """Velocity of the contact point on b relative to the one on a."""
    return (vbx - wb * rby) - (vax - wa * ray), (vby + wb * rbx) - (vay + wa * rax)


def current_separation(layout: ContactLayout, cc: ContactConstraints, pose: Pose, pose0: Pose, token):
    """Packed (C, 2, K, *batch) separation after the bodies moved from pose0 to pose, anchors rotated with them.

    Runs inside the substeps on batch-last arrays (see step.py): per-body (M, *batch), per-slot (S, *batch).
    token: a traced non-negative integer, the substep (see math2d.stored).
    """
    a, b = layout.slot_a, layout.slot_b

    def per_body(pose, pose0):
        da = pose.a - pose0.a
        return jnp.stack([pose.x - pose0.x, pose.y - pose0.y, jnp.cos(da), jnp.sin(da)])

    # Each body's move as one stored (4, M, *batch) array, so the cosine and sine are computed per
    # body (M of them) rather than per slot and point (M^2 - M), which fused into the gathers by slot.
    move = stored(token, per_body, pose, pose0)

    def moved_anchor(i, rx, ry):
        dx, dy, cos, sin = (m[:, None] for m in take_rows(move, i, axis=1))
        qx, qy = rotate(cos, sin, rx, ry)
        return dx + qx, dy + qy

    pax, pay = moved_anchor(a, cc.rax, cc.ray)
    pbx, pby = moved_anchor(b, cc.rbx, cc.rby)
    sep = (pbx - pax) * cc.nx[:, None] + (pby - pay) * cc.ny[:, None] + cc.base_separation
    return pack_rows(layout, [sep[:, 0], sep[:, 1]])


# Packed layout. Inside the sweeps every per-slot quantity is one row of a colour-major
# (C, F, K) array: the scan slices one (F, K) block per colour, each field a contiguous row
# of the colour's K slots. Constraint data is packed once per step; impulses stay packed
# through all substeps.
#
# A colour's velocities are the (3, 2K) rows the sweep gathers, viewed as six rows of K (VEL_ROWS).
# An impulse p along a point's normal or tangent changes them by p times six constant rows, its
# push rows (the inverse masses times the constraint's Jacobian), which prepare packs once per
# step: a velocity update is then one elementwise kernel over contiguous rows.
VEL_ROWS = ("xa", "xb", "ya", "yb", "wa", "wb")  # x of side a, x of side b, y of a, y of b, w of a, w of b
PUSH_ROWS = {(kind, k): tuple(f"{kind}{k}_{v}" for v in VEL_ROWS) for kind in ("normal", "tangent") for k in range(2)}
CONST_ROWS = ("nx", "ny", "friction", "restitution", "gn",
              "rax0", "rax1", "ray0", "ray1", "rbx0", "rbx1", "rby0", "rby1",
              "nmass0", "nmass1", "tmass0", "tmass1", "rel0", "rel1", "boost0", "boost1") + sum(PUSH_ROWS.values(), ())
IMPULSE_ROWS = ("n0", "n1", "t0", "t1", "max0", "max1")
_ROW = {name: i for i, name in enumerate(CONST_ROWS)}
_N, _T, _MAX = 0, 2, 4  # first impulse row of the normal, tangent and largest normal impulses


def pack_rows(layout: ContactLayout, rows) -> jax.Array:
    """A list of (S, *batch) arrays, slot order -> (C, F, K, *batch), solve order."""
    C, K = layout.num_colours, layout.per_colour
    stacked = jnp.stack(rows).astype(jnp.float32)
    if layout.walls_repeat:
        stacked = take_rows(stacked, layout.solve_slots, axis=1)
    return jnp.swapaxes(stacked.reshape((len(rows), C, K) + stacked.shape[2:]), 0, 1)


def unpack_rows(layout: ContactLayout, packed) -> jax.Array:
    """(C, F, K, *batch), solve order -> (F, S, *batch), slot order."""
    C, F, K = packed.shape[:3]
    rows = jnp.swapaxes(packed, 0, 1).reshape((F, C * K) + packed.shape[3:])
    return take_rows(rows, layout.slot_order, axis=1) if layout.walls_repeat else rows


def _push_rows(cc: ContactConstraints, k: int, dx, dy) -> list:
    """The change of VEL_ROWS per unit impulse along (dx, dy) at point k: -p on side a, +p on side b."""
    return [-cc.ma * dx, cc.mb * dx, -cc.ma * dy, cc.mb * dy,
            -cc.ia * cross(cc.rax[:, k], cc.ray[:, k], dx, dy), cc.ib * cross(cc.rbx[:, k], cc.rby[:, k], dx, dy)]


def pack_constraints(layout: ContactLayout, cc: ContactConstraints) -> jax.Array:
    per_point = (cc.rax, cc.ray, cc.rbx, cc.rby, cc.normal_mass, cc.tangent_mass, cc.relative_velocity,
                 cc.impact_boost)
    rows = [cc.nx, cc.ny, cc.friction, cc.restitution, cc.normal_gravity]
    rows += [x[:, k] for x in per_point for k in range(2)]
    direction = {"normal": (cc.nx, cc.ny), "tangent": (cc.ny, -cc.nx)}
    for kind, k in PUSH_ROWS:
        rows += _push_rows(cc, k, *direction[kind])
    return pack_rows(layout, rows)


def pack_impulses(layout: ContactLayout, imp: ContactImpulses) -> jax.Array:
    return pack_rows(layout, [x[:, k] for x in imp for k in range(2)])


def unpack_impulses(layout: ContactLayout, packed) -> ContactImpulses:
    rows = unpack_rows(layout, packed)
    return ContactImpulses(*(jnp.stack([rows[i], rows[i + 1]], axis=1) for i in range(0, 6, 2)))


class _Rows:
    """Colour c's rows of a packed (C, F, K, *batch) array, read row by row where they are used.

    Each read is a dynamic slice that XLA fuses into the kernel reading it; slicing the colour's
    whole (F, K) block first made the solver copy it in every colour of every sweep, because
    the conditionals that read a few of its rows take the block as an operand.
    """

    def __init__(self, packed, c):
        self.packed, self.c = packed, c

    def __getitem__(self, i):
        return at(self.packed[:, i], self.c)


class _Block(_Rows):
    """Named access to colour c's constant rows (CONST_ROWS)."""

    def __getattr__(self, name):
        if name.startswith("__"):  # copy and pickle probe for these
            raise AttributeError(name)
        return self[_ROW[name]]

    def point(self, name, k: int):
        """Row of point k."""
        return self[_ROW[f"{name}{k}"]]

    def push(self, kind: str, k: int):
        """(6, K, *batch) the push rows of point k's normal or tangent."""
        i = _ROW[PUSH_ROWS[(kind, k)][0]]
        return self[i:i + len(VEL_ROWS)]


class Schedule(NamedTuple):
    """Which colours a step's sweeps visit: the first `count` entries of `order`, in colour order."""

    order: jax.Array  # (C,) int32: the live colours first (ascending), then the others
    count: jax.Array  # () int32: how many colours are live
    points: jax.Array  # (C,) int32: 2 if a slot of the colour has a second point in some scene, else 1


def schedule(const) -> Schedule:
    """The colours with a point in any scene of the batch (packed const, batch-last).

    A colour with no point has zero masses and zero impulses, so solving it changes nothing
    and the sweeps skip it. Most colours are empty in a real level (the reference levels
    touch 3 of 7, 9 and 15 on average), so this makes a step at a small batch much cheaper;
    a batch of very different scenes skips only the colours empty in all of them.

    Likewise a colour's second point is skipped where no slot of it has one in any scene
    (contacts with a circle have one point): solving an absent point changes nothing.
    """
    i = _ROW["nmass0"]
    masses = const[:, i:i + 2]
    live = jnp.any(masses > 0.0, axis=tuple(range(1, masses.ndim)))
    order = jnp.argsort(~live, stable=True).astype(jnp.int32)
    second = jnp.any(masses[:, 1] > 0.0, axis=tuple(range(1, masses.ndim - 1)))
    return Schedule(order, jnp.sum(live, dtype=jnp.int32), 1 + second.astype(jnp.int32))


def _sweep(layout: ContactLayout, vel: Vel, solve_colour, const, impulses, plan: Schedule, *inputs):
    """Run `solve_colour(vels, lam, points, const_block, *input_rows) -> (vels, lam)` on every live
    colour in order. vels: the colour's (6, K, *batch) VEL_ROWS; lam: its (6, K, *batch) impulse
    rows; points: how many of the two points any slot of the colour has; const_block and
    input_rows: the colour's rows of const and of each packed (C, F, K, *batch) input. A
    solve_colour that changes no impulse returns lam None.

    A loop over the schedule's live colours: each iteration gathers the velocities of the K bodies
    of side a and the K of side b as one (3, 2K, *batch) array, solves, and writes them back by a
    gather (layout.write_back). One array rather than six: each gather and velocity update is then
    one kernel, and a step at a small batch is a long chain of such small kernels. Skipped colours
    keep their impulses, which is what solving them would give.
    Returns the velocities and the packed (C, 6, K, *batch) impulses.
    """
    K = layout.per_colour
    sides, write_back = jnp.asarray(layout.solve_sides), jnp.asarray(layout.write_back)
    stacked = jnp.stack(vel)  # (3, M, *batch)
    batch = stacked.shape[2:]
    if sides.ndim == 3:  # (C, 2K, B): each scene its own sides (broad_phase); flat indices into (3, M * B)
        sides, write_back = scene_rows(sides, batch[0]), scene_rows(write_back, batch[0])
        gather = gather_scene_rows
    else:
        def gather(v, idx):
            return v[:, idx]

    def colour(v, lam, c):
        vels = gather(v, at(sides, c)).reshape((6, K) + batch)
        vels, lam = solve_colour(vels, lam, at(plan.points, c), _Block(const, c), *(_Rows(x, c) for x in inputs))
        return gather(jnp.concatenate([v, vels.reshape((3, 2 * K) + batch)], axis=1), at(write_back, c)), lam

    def body(i, carry):
        v, out = carry
        c = at(plan.order, i)
        # Read from the input, not the carry: reading a slice of the array the loop updates in place
        # made XLA copy all of it in every iteration.
        v, lam = colour(v, at(impulses, c), c)
        return v, set_at(out, c, lam)

    def body_same_impulses(i, v):
        c = at(plan.order, i)
        return colour(v, at(impulses, c), c)[0]

    probe = jax.eval_shape(lambda: solve_colour(jnp.zeros((6, K) + batch), impulses[0], 2, _Block(const, 0),
                                                *(_Rows(x, 0) for x in inputs))[1])
    if probe is None:
        v = jax.lax.fori_loop(0, plan.count, body_same_impulses, stacked)
    else:
        v, impulses = jax.lax.fori_loop(0, plan.count, body, (stacked, impulses))
    return Vel(v[0], v[1], v[2]), impulses


def _sides(vels) -> tuple[Vel, Vel]:
    """A colour's VEL_ROWS as the velocities of side a and of side b."""
    return Vel(vels[0], vels[2], vels[4]), Vel(vels[1], vels[3], vels[5])


def _with_rows(lam, rows: dict) -> jax.Array:
    """lam (6, K, *batch) impulse rows with the rows in `rows` ({row: value}) replaced: an elementwise
    select, so that the update stays one kernel (a stack of rows compiled to one per row)."""
    index = jnp.arange(lam.shape[0]).reshape((-1,) + (1,) * (lam.ndim - 1))
    for row, value in rows.items():
        lam = jnp.where(index == row, value[None], lam)
    return lam


def _for_points(points, row: int, accumulated, push, vels, lam):
    """Solve one impulse row of the points k < `points` of a colour, point by point.

    accumulated(k, vels, lam) -> the new accumulated impulse of row `row + k`; push(k, vels, lam, new)
    -> the velocities and impulses with it applied. The first is the branch of a conditional
    (k < points), so the impulse is computed once and stored: XLA's CPU fusion copies a chain of
    elementwise operations into each of its consumers, which would recompute it for every row it
    changes. Point 0's condition always holds for a live colour; XLA cannot know that, so it stays
    a conditional too. An absent point keeps its impulse, so push changes nothing.

    A point's update is then three kernels; a point loop over separate arrays took about 18.
    """
    for k in range(2):
        new = jax.lax.cond(points > k, functools.partial(accumulated, k), lambda v, lam, r=row + k: lam[r], vels, lam)
        vels, lam = push(k, vels, lam, new)
    return vels, lam


def _push(c: _Block, kind: str, row: int, k: int, vels, lam, new, track_max: bool = False):
    """Apply point k's new accumulated impulse `new` of impulse row `row + k` (its normal or tangent, `kind`):
    the velocities change by the push rows times the difference, the row takes `new`, and with
    `track_max` the point's largest normal impulse so far is kept (restitution reads it)."""
    impulse = new - lam[row + k]
    rows = {row + k: new}
    if track_max:
        rows[_MAX + k] = jnp.maximum(lam[_MAX + k], impulse)
    return vels + c.push(kind, k) * impulse[None], _with_rows(lam, rows)


def _velocity_along(c: _Block, k: int, vels, dx, dy):
    """Relative velocity at point k along (dx, dy)."""
    va, vb = _sides(vels)
    rax, ray, rbx, rby = c.point("rax", k), c.point("ray", k), c.point("rbx", k), c.point("rby", k)
    dvx, dvy = _relative_velocity(va.x, va.y, va.w, vb.x, vb.y, vb.w, rax, ray, rbx, rby)
    return dvx * dx + dvy * dy


def warm_start(layout: ContactLayout, const, impulses, vel: Vel, plan: Schedule) -> Vel:
    """Re-apply the accumulated impulses before solving.

    A sweep over the colours rather than one scatter-add: the sum on each body then
    always runs in colour order (the same for every batch width and every run of a program).
    """

    def apply_colour(vels, lam, points, c: _Block):
        for row, (kind, k) in ((_N, ("normal", 0)), (_N + 1, ("normal", 1)), (_T, ("tangent", 0)),
                               (_T + 1, ("tangent", 1))):
            vels = vels + c.push(kind, k) * lam[row][None]
        return vels, None

    return _sweep(layout, vel, apply_colour, const, impulses, plan)[0]


def solve(layout: ContactLayout, const, impulses, vel: Vel, separation, softness: Softness, inv_h, max_push,
          use_bias: bool, plan: Schedule) -> tuple[Vel, jax.Array]:
    """One Gauss-Seidel sweep of normal then friction constraints over all colours.

    const: packed constraints; impulses: packed (C, 6, K); separation: packed (C, 2, K).
    """

    def normal(c: _Block, sep, k, vels, lam):
        vn = _velocity_along(c, k, vels, c.nx, c.ny)
        s = sep[k]
        speculative = s > 0.0
        if use_bias:
            bias = jnp.where(speculative, s * inv_h, jnp.maximum(softness.bias_rate * s, -max_push))
            mass_scale = jnp.where(speculative, 1.0, softness.mass_scale)
            impulse_scale = jnp.where(speculative, 0.0, softness.impulse_scale)
        else:
            bias = jnp.where(speculative, s * inv_h, 0.0)
            mass_scale, impulse_scale = 1.0, 0.0
        old = lam[_N + k]
        return jnp.maximum(old - c.point("nmass", k) * mass_scale * (vn + bias) - impulse_scale * old, 0.0)

    def friction(c: _Block, k, vels, lam):
        vt = _velocity_along(c, k, vels, c.ny, -c.nx)
        limit = c.friction * lam[_N + k]
        return jnp.clip(lam[_T + k] - c.point("tmass", k) * vt, -limit, limit)

    def solve_colour(vels, lam, points, c: _Block, sep: _Rows):
        vels, lam = _for_points(points, _N, functools.partial(normal, c, sep),
                                functools.partial(_push, c, "normal", _N, track_max=True), vels, lam)
        return _for_points(points, _T, functools.partial(friction, c), functools.partial(_push, c, "tangent", _T),
                           vels, lam)

    return _sweep(layout, vel, solve_colour, const, impulses, plan, separation)
