"""Contact constraints: prepare, warm start, solve / relax, restitution, store.

The stages follow Box2D v3's soft step (Catto, "Solver2D", 2024). Contacts are
prepared once per step from the narrow phase. Each substep then warm starts,
solves with a soft position bias, integrates positions and relaxes without the
bias; restitution runs once at the end.

Slots are solved colour by colour (see pairs.py): within a colour no body
appears twice, so a colour is one vectorised update and the sweep is an exact
Gauss-Seidel pass. Colours without any point are skipped (see schedule).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jax2d.math2d import Pose, Softness, Vel, cross, rotate, safe_inverse, stored
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


class ContactImpulses(NamedTuple):
    normal: jax.Array  # (S, 2)
    tangent: jax.Array  # (S, 2)
    max_normal: jax.Array  # (S, 2) largest normal impulse applied this step


def prepare(layout: ContactLayout, manifold, valid, pose: Pose, vel: Vel, inv_mass, inv_inertia,
            friction, restitution) -> ContactConstraints:
    """Build constraints from the step's manifolds (one row per slot), on batch-last arrays:
    per body (M, *batch), manifold fields with the batch after their own axes."""
    a, b = layout.slot_a, layout.slot_b
    nx, ny = manifold.normal[:, 0], manifold.normal[:, 1]
    px, py = manifold.point[:, :, 0], manifold.point[:, :, 1]
    rax, ray = px - pose.x[a][:, None], py - pose.y[a][:, None]
    rbx, rby = px - pose.x[b][:, None], py - pose.y[b][:, None]
    ma, ia, mb, ib = inv_mass[a], inv_inertia[a], inv_mass[b], inv_inertia[b]
    n_x, n_y = nx[:, None], ny[:, None]
    base = manifold.separation - ((rbx - rax) * n_x + (rby - ray) * n_y)

    def effective_mass(dx, dy):
        rna, rnb = cross(rax, ray, dx, dy), cross(rbx, rby, dx, dy)
        k = (ma + mb)[:, None] + ia[:, None] * rna**2 + ib[:, None] * rnb**2
        return jnp.where(valid, safe_inverse(k), 0.0)

    dvx, dvy = _relative_velocity(vel.x[a][:, None], vel.y[a][:, None], vel.w[a][:, None],
                                  vel.x[b][:, None], vel.y[b][:, None], vel.w[b][:, None], rax, ray, rbx, rby)
    return ContactConstraints(
        nx=nx, ny=ny,
        friction=jnp.sqrt(friction[a] * friction[b]),
        restitution=jnp.maximum(restitution[a], restitution[b]),
        ma=ma, ia=ia, mb=mb, ib=ib,
        rax=rax, ray=ray, rbx=rbx, rby=rby,
        base_separation=base,
        normal_mass=effective_mass(n_x, n_y),
        tangent_mass=effective_mass(n_y, -n_x),
        relative_velocity=dvx * n_x + dvy * n_y,
    )


def _relative_velocity(vax, vay, wa, vbx, vby, wb, rax, ray, rbx, rby):
    """Velocity of the contact point on b relative to the one on a."""
    return (vbx - wb * rby) - (vax - wa * ray), (vby + wb * rbx) - (vay + wa * rax)


def current_separation(layout: ContactLayout, cc: ContactConstraints, pose: Pose, pose0: Pose):
    """Packed (C, 2, K, *batch) separation after the bodies moved from pose0 to pose, anchors rotated with them.

    Runs inside the substeps on batch-last arrays (see step.py): per-body (M, *batch), per-slot (S, *batch).
    """
    a, b = layout.slot_a, layout.slot_b

    def moved_anchor(i, rx, ry):
        da = (pose.a - pose0.a)[i][:, None]
        qx, qy = rotate(jnp.cos(da), jnp.sin(da), rx, ry)
        return (pose.x - pose0.x)[i][:, None] + qx, (pose.y - pose0.y)[i][:, None] + qy

    pax, pay = moved_anchor(a, cc.rax, cc.ray)
    pbx, pby = moved_anchor(b, cc.rbx, cc.rby)
    sep = (pbx - pax) * cc.nx[:, None] + (pby - pay) * cc.ny[:, None] + cc.base_separation
    return pack_rows(layout, [sep[:, 0], sep[:, 1]])


# Packed layout. Inside the sweeps every per-slot quantity is one row of a colour-major
# (C, F, K) array: the scan slices one (F, K) block per colour, each field a contiguous row
# of the colour's K slots. Constraint data is packed once per step; impulses stay packed
# through all substeps.
CONST_ROWS = ("nx", "ny", "friction", "restitution", "ma", "ia", "mb", "ib",
              "rax0", "rax1", "ray0", "ray1", "rbx0", "rbx1", "rby0", "rby1",
              "nmass0", "nmass1", "tmass0", "tmass1", "rel0", "rel1")
IMPULSE_ROWS = ("n0", "n1", "t0", "t1", "max0", "max1")
_ROW = {name: i for i, name in enumerate(CONST_ROWS)}


def pack_rows(layout: ContactLayout, rows) -> jax.Array:
    """A list of (S, *batch) arrays, slot order -> (C, F, K, *batch), solve order."""
    C, K = layout.num_colours, layout.per_colour
    stacked = jnp.stack(rows).astype(jnp.float32)
    if layout.walls_repeat:
        stacked = stacked[:, layout.solve_slots]
    return jnp.swapaxes(stacked.reshape((len(rows), C, K) + stacked.shape[2:]), 0, 1)


def unpack_rows(layout: ContactLayout, packed) -> jax.Array:
    """(C, F, K, *batch), solve order -> (F, S, *batch), slot order."""
    C, F, K = packed.shape[:3]
    rows = jnp.swapaxes(packed, 0, 1).reshape((F, C * K) + packed.shape[3:])
    return rows[:, np.argsort(layout.solve_slots)] if layout.walls_repeat else rows


def pack_constraints(layout: ContactLayout, cc: ContactConstraints) -> jax.Array:
    per_point = (cc.rax, cc.ray, cc.rbx, cc.rby, cc.normal_mass, cc.tangent_mass, cc.relative_velocity)
    rows = [cc.nx, cc.ny, cc.friction, cc.restitution, cc.ma, cc.ia, cc.mb, cc.ib]
    rows += [x[:, k] for x in per_point for k in range(2)]
    return pack_rows(layout, rows)


def pack_impulses(layout: ContactLayout, imp: ContactImpulses) -> jax.Array:
    return pack_rows(layout, [x[:, k] for x in imp for k in range(2)])


def unpack_impulses(layout: ContactLayout, packed) -> ContactImpulses:
    rows = unpack_rows(layout, packed)
    return ContactImpulses(*(jnp.stack([rows[i], rows[i + 1]], axis=1) for i in range(0, 6, 2)))


class _Block:
    """Named access to one colour's constant rows."""

    def __init__(self, block):
        self.block = block

    def __getattr__(self, name):
        return self.block[_ROW[name]]

    def point(self, name, k):
        """Row of point k (k may be traced: both points' rows are adjacent)."""
        i = _ROW[f"{name}0"]
        return self.block[i:i + 2][k]


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

    Likewise the point loops stop after the first point in a colour where no slot has a second
    one in any scene (contacts with a circle have one point): solving an absent point changes
    nothing.
    """
    i = _ROW["nmass0"]
    masses = const[:, i:i + 2]
    live = jnp.any(masses > 0.0, axis=tuple(range(1, masses.ndim)))
    order = jnp.argsort(~live, stable=True).astype(jnp.int32)
    second = jnp.any(masses[:, 1] > 0.0, axis=tuple(range(1, masses.ndim - 1)))
    return Schedule(order, jnp.sum(live, dtype=jnp.int32), 1 + second.astype(jnp.int32))


def _sweep(layout: ContactLayout, vel: Vel, solve_colour, const, var, plan: Schedule):
    """Run `solve_colour(sides, const_block, var_block, points) -> (sides, new_var_block)` on every live
    colour in order (points: how many of the two points any slot of the colour has).

    A loop over the schedule's live colours: each iteration gathers the velocities of the K bodies
    of side a and the K of side b as one (3, 2K, *batch) array (see _split / _join), solves, and
    writes them back. One array rather than six: each gather, scatter and velocity update is then
    one kernel, and a step at a small batch is a long chain of such small kernels. Skipped
    colours keep the first rows of their var block, which is what solving them would give.
    Returns the velocities and the (C, F_out, K, *batch) new var blocks.
    """
    K = layout.per_colour
    sides = jnp.asarray(layout.solve_sides)
    stacked = jnp.stack(vel)  # (3, M, *batch)
    rows = jax.eval_shape(lambda: solve_colour(stacked[:, :2 * K], _Block(const[0]), var[0], 2)[1]).shape[0]

    def body(i, carry):
        v, out = carry
        c = plan.order[i]
        index = sides[c]
        both, new = solve_colour(v[:, index], _Block(const[c]), var[c], plan.points[c])
        # Only an always-static body appears twice in a colour (layout.walls_repeat), and its
        # velocity is unchanged by every slot (zero inverse mass): overlapping writes agree.
        return v.at[:, index].set(both, unique_indices=not layout.walls_repeat), out.at[c].set(new)

    v, out = jax.lax.fori_loop(0, plan.count, body, (stacked, var[:, :rows]))
    return Vel(v[0], v[1], v[2]), out


def _split(both) -> tuple[Vel, Vel]:
    """(3, 2K, *batch) velocities of a colour's two sides -> side a, side b."""
    K = both.shape[1] // 2
    return Vel(both[0, :K], both[1, :K], both[2, :K]), Vel(both[0, K:], both[1, K:], both[2, K:])


def _join(va: Vel, vb: Vel):
    """The inverse of _split."""
    return jnp.stack([jnp.concatenate([a, b]) for a, b in zip(va, vb, strict=True)])


def _apply(va: Vel, vb: Vel, ma, ia, mb, ib, rax, ray, rbx, rby, px, py):
    """Apply impulse (px, py) to b and its opposite to a, at the given anchors."""
    va = Vel(va.x - ma * px, va.y - ma * py, va.w - ia * cross(rax, ray, px, py))
    vb = Vel(vb.x + mb * px, vb.y + mb * py, vb.w + ib * cross(rbx, rby, px, py))
    return va, vb


def warm_start(layout: ContactLayout, const, impulses, vel: Vel, plan: Schedule) -> Vel:
    """Re-apply the accumulated impulses before solving.

    A sweep over the colours rather than one scatter-add: the sum on each body then
    always runs in colour order (the same for every batch width and every run of a program).
    """

    def apply_colour(both, c: _Block, var, points):
        va, vb = _split(both)
        tx, ty = c.ny, -c.nx
        for k in range(2):
            px = var[k] * c.nx + var[2 + k] * tx
            py = var[k] * c.ny + var[2 + k] * ty
            va, vb = _apply(va, vb, c.ma, c.ia, c.mb, c.ib, c.point("rax", k), c.point("ray", k),
                            c.point("rbx", k), c.point("rby", k), px, py)
        return _join(va, vb), var

    return _sweep(layout, vel, apply_colour, const, impulses, plan)[0]


def solve(layout: ContactLayout, const, impulses, vel: Vel, separation, softness: Softness, inv_h, max_push,
          use_bias: bool, plan: Schedule) -> tuple[Vel, jax.Array]:
    """One Gauss-Seidel sweep of normal then friction constraints over all colours.

    const: packed constraints; impulses: packed (C, 6, K); separation: packed (C, 2, K).
    Within a colour the two points are loops, not unrolled: a loop boundary stores its
    carry, which stops XLA from re-deriving each output from the whole chain of updates;
    inside a point, `stored` does the same for the new accumulated impulse.
    """

    def normal(k, carry, c: _Block, sep):
        both, lam_n, lam_max = carry
        va, vb = _split(both)
        rax, ray, rbx, rby = c.point("rax", k), c.point("ray", k), c.point("rbx", k), c.point("rby", k)
        dvx, dvy = _relative_velocity(va.x, va.y, va.w, vb.x, vb.y, vb.w, rax, ray, rbx, rby)
        vn = dvx * c.nx + dvy * c.ny
        s = sep[k]
        speculative = s > 0.0
        if use_bias:
            bias = jnp.where(speculative, s * inv_h, jnp.maximum(softness.bias_rate * s, -max_push))
            mass_scale = jnp.where(speculative, 1.0, softness.mass_scale)
            impulse_scale = jnp.where(speculative, 0.0, softness.impulse_scale)
        else:
            bias = jnp.where(speculative, s * inv_h, 0.0)
            mass_scale, impulse_scale = 1.0, 0.0
        old = lam_n[k]

        def accumulate(vn, old, bias, mass_scale, impulse_scale):
            return jnp.maximum(old - c.point("nmass", k) * mass_scale * (vn + bias) - impulse_scale * old, 0.0)

        new = stored(k, accumulate, vn, old, bias, mass_scale, impulse_scale)
        impulse = new - old
        va, vb = _apply(va, vb, c.ma, c.ia, c.mb, c.ib, rax, ray, rbx, rby, impulse * c.nx, impulse * c.ny)
        return _join(va, vb), lam_n.at[k].set(new), lam_max.at[k].set(jnp.maximum(lam_max[k], impulse))

    def friction(k, carry, c: _Block, lam_n):
        both, lam_t = carry
        va, vb = _split(both)
        tx, ty = c.ny, -c.nx
        rax, ray, rbx, rby = c.point("rax", k), c.point("ray", k), c.point("rbx", k), c.point("rby", k)
        dvx, dvy = _relative_velocity(va.x, va.y, va.w, vb.x, vb.y, vb.w, rax, ray, rbx, rby)
        vt = dvx * tx + dvy * ty
        limit = c.friction * lam_n[k]
        old = lam_t[k]
        new = stored(k, lambda old, vt, limit: jnp.clip(old - c.point("tmass", k) * vt, -limit, limit), old, vt, limit)
        impulse = new - old
        va, vb = _apply(va, vb, c.ma, c.ia, c.mb, c.ib, rax, ray, rbx, rby, impulse * tx, impulse * ty)
        return _join(va, vb), lam_t.at[k].set(new)

    def solve_colour(both, c: _Block, var, points):
        both, lam_n, lam_max = jax.lax.fori_loop(
            0, points, lambda k, carry: normal(k, carry, c, var[6:8]), (both, var[0:2], var[4:6]))
        both, lam_t = jax.lax.fori_loop(0, points, lambda k, carry: friction(k, carry, c, lam_n), (both, var[2:4]))
        return both, jnp.concatenate([lam_n, lam_t, lam_max])

    return _sweep(layout, vel, solve_colour, const, jnp.concatenate([impulses, separation], axis=1), plan)


def restitution(layout: ContactLayout, const, impulses, vel: Vel, threshold, plan: Schedule) -> tuple[Vel, jax.Array]:
    """Make approaching points that hit faster than `threshold` leave at e times their approach speed."""

    def hits(rel, lam_max, restitution):
        """Which points bounce: approaching faster than the threshold, pushed this step, restitution > 0."""
        return (rel < -threshold) & (lam_max > 0.0) & (restitution > 0.0)

    def bounce(k, carry, c: _Block, lam_max):
        both, lam_n = carry
        va, vb = _split(both)
        rel = c.point("rel", k)
        hit = hits(rel, lam_max[k], c.restitution)
        rax, ray, rbx, rby = c.point("rax", k), c.point("ray", k), c.point("rbx", k), c.point("rby", k)
        dvx, dvy = _relative_velocity(va.x, va.y, va.w, vb.x, vb.y, vb.w, rax, ray, rbx, rby)
        vn = dvx * c.nx + dvy * c.ny
        old = lam_n[k]
        new = stored(k, lambda old, vn: jnp.maximum(
            old + jnp.where(hit, -c.point("nmass", k) * (vn + c.restitution * rel), 0.0), 0.0), old, vn)
        impulse = new - old
        va, vb = _apply(va, vb, c.ma, c.ia, c.mb, c.ib, rax, ray, rbx, rby, impulse * c.nx, impulse * c.ny)
        return _join(va, vb), lam_n.at[k].set(new)

    def solve_colour(both, c: _Block, var, points):
        both, lam_n = jax.lax.fori_loop(0, points, lambda k, carry: bounce(k, carry, c, var[4:6]), (both, var[0:2]))
        return both, jnp.concatenate([lam_n, var[2:]])

    # Most steps bounce nowhere in the batch; then the sweep would change nothing (every impulse
    # stays as it is), so it is skipped: a few hundred small kernels per step at a small batch.
    hit = hits(const[:, _ROW["rel0"]:_ROW["rel0"] + 2], impulses[:, 4:6], const[:, None, _ROW["restitution"]])
    return jax.lax.cond(jnp.any(hit), lambda: _sweep(layout, vel, solve_colour, const, impulses, plan),
                        lambda: (vel, impulses))
