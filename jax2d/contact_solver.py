"""Contact constraints: prepare, warm start, solve / relax, store (restitution: restitution.py).

The stages follow Box2D v3's soft step (Catto, "Solver2D", 2024). Contacts are
prepared once per step from the narrow phase. Each substep then warm starts,
solves with a soft position bias, integrates positions and relaxes without the
bias; restitution runs once at the end (restitution.py, on these sweeps).

Slots are solved colour by colour (see pairs.py): within a colour no body
appears twice, so a colour is one vectorised update and the sweep is an exact
Gauss-Seidel pass. Colours without any point are skipped (sweeps.schedule). The
packed rows and the sweep itself are in sweeps.py.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jax2d.loads import resting_loads
from jax2d.math2d import Pose, Softness, Vel, cross, rotate, safe_inverse, stored, take_rows
from jax2d.pairs import ContactLayout
from jax2d.state import Contacts
from jax2d.sweeps import (
    NORMAL,
    PUSH_ROWS,
    TANGENT,
    Block,
    Chain,
    ImpulseRow,
    Rows,
    Schedule,
    apply_impulse,
    for_points,
    pack_rows,
    relative_velocity,
    sweep,
    unpack_rows,
    velocity_along,
)

# Contacts under a load are stiffened so that at rest they sink at most this many linear slops (load_softness):
# 4 mm. At 0.5 slop a 100:1 stack on the levels' floor rocked apart; at 1 slop it held too, with 5 mm.
LOADED_SAG = 0.8


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
    mass_scale: jax.Array  # (S, 2) the soft solve's mass scale per point (load_softness); its impulse scale is 1 - it
    stiff: jax.Array  # (S, 2) 1 where load_softness stiffened the point, else 0
    weight: jax.Array  # (S, 2) the resting load per point and substep (loads.resting_loads), for new stiff points


class ContactImpulses(NamedTuple):
    normal: jax.Array  # (S, 2)
    tangent: jax.Array  # (S, 2)
    max_normal: jax.Array  # (S, 2) largest normal impulse applied this step


def prepare(layout: ContactLayout, manifold, valid, pose: Pose, vel: Vel, inv_mass, inv_inertia,
            friction, restitution, gravity, h, softness: Softness, slop) -> ContactConstraints:
    """Build constraints from the step's manifolds (one row per slot), on batch-last arrays:
    per body (M, *batch), manifold fields with the batch after their own axes; gravity (2, *batch);
    h: the substep; softness: the contacts' (math2d.soft); slop: (*batch) SimParams.linear_slop."""
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

    dvx, dvy = relative_velocity(ta(vel.x)[:, None], ta(vel.y)[:, None], ta(vel.w)[:, None],
                                  tb(vel.x)[:, None], tb(vel.y)[:, None], tb(vel.w)[:, None], rax, ray, rbx, rby)
    rel = dvx * n_x + dvy * n_y
    acc = normal_gravity(nx, ny, ma, mb, gravity)
    normal_mass = effective_mass(n_x, n_y)
    touching = jnp.any(valid, axis=1)
    points = jnp.sum(valid, axis=1).astype(jnp.float32)
    weight = (resting_loads(a, b, nx, ny, inv_mass, gravity, touching) * h * safe_inverse(points))[:, None]
    weight = jnp.where(valid, weight, 0.0)
    mass_scale, stiff = load_softness(softness, normal_mass, weight, LOADED_SAG * slop)
    return ContactConstraints(
        nx=nx, ny=ny,
        friction=jnp.sqrt(ta(friction) * tb(friction)),
        restitution=jnp.maximum(ta(restitution), tb(restitution)),
        ma=ma, ia=ia, mb=mb, ib=ib,
        rax=rax, ray=ray, rbx=rbx, rby=rby,
        base_separation=base,
        normal_mass=normal_mass,
        tangent_mass=effective_mass(n_y, -n_x),
        relative_velocity=rel,
        impact_boost=_impact_boost(rel, manifold.separation, acc[:, None], h),
        normal_gravity=acc,
        mass_scale=mass_scale,
        stiff=stiff,
        weight=weight,
    )


def load_softness(softness: Softness, normal_mass, load, max_sag) -> tuple[jax.Array, jax.Array]:
    """(S, 2, *batch) per point: the soft solve's mass scale, stiffened where the point's resting load would sink
    it deeper than max_sag, and 1 where it was stiffened (else 0).

    A soft contact is a spring of stiffness m_n w^2 (m_n the point's normal mass): at rest under the impulse
    lambda per substep its overlap is lambda / (m_n h w^2) = lambda / (m_n b a2), with b the bias rate and
    a2 = mass_scale / impulse_scale (math2d.soft). A light body carrying a heavy one (100 kg on 1 kg) carries
    100 times its own weight on its own normal mass, and sank 100 times deeper than under its own weight:
    8.7 mm at 60 Hz, 9-18 mm for other sizes and stacks. Where a point's overlap would exceed max_sag, a2 is
    raised so that it does not, with the bias rate kept: w and the damping ratio grow by the same factor, so
    the point still closes an overlap at the same rate and only its give under the load shrinks.
    load: the resting load per point and substep (loads.resting_loads), an estimate from the masses and which
    pairs touch; stiffening by last step's impulses instead (Box2D-like warm starting) pumped energy into a
    settling stack (a lagged stiffness stores less than it gives back) and it rocked apart. Stiff points need
    more Gauss-Seidel passes than the substeps' one solve and one relax (a 100:1 stack stiffened 1.5-2x without
    them fell apart in seconds), which SolverConfig.stiff_solve_iterations and stiff_relax_iterations give them
    (solve with a Chain plan)."""
    a2 = softness.mass_scale / softness.impulse_scale
    needed = load * safe_inverse(normal_mass * softness.bias_rate * max_sag)
    stiff = (needed > a2) & (normal_mass > 0.0)
    x = jnp.where(stiff, needed, a2)
    return jnp.where(stiff, x / (1.0 + x), softness.mass_scale), stiff.astype(jnp.float32)


def matched_impulses(old: Contacts, key, valid, warm_start: bool) -> ContactImpulses:
    """Last step's impulses for points whose feature key is unchanged (either slot), else 0."""
    zeros = jnp.zeros(key.shape, jnp.float32)
    if not warm_start:
        return ContactImpulses(zeros, zeros, zeros)
    same = (key == old.key) & old.active
    swapped = (key == old.key[:, ::-1]) & old.active[:, ::-1]

    def pick(x):
        return jnp.where(valid, jnp.where(same, x, jnp.where(swapped, x[:, ::-1], 0.0)), 0.0)

    return ContactImpulses(pick(old.normal_impulse), pick(old.tangent_impulse), zeros)


def seed_impulses(imp: ContactImpulses, cc: ContactConstraints) -> ContactImpulses:
    """The warm start, with a stiffened point that has no impulse from last step (a new contact) starting from
    its resting load (loads.resting_loads). Gauss-Seidel passes move a heavy body on a light one only by about
    the mass ratio per pass, so a new 100:1 stack started from 0 let the heavy box drop into the light one
    before its support had built up."""
    fresh = (imp.normal == 0.0) & (cc.stiff > 0.0)
    return imp._replace(normal=jnp.where(fresh, cc.weight, imp.normal))


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


def _push_rows(cc: ContactConstraints, k: int, dx, dy) -> list:
    """The change of VEL_ROWS per unit impulse along (dx, dy) at point k: -p on side a, +p on side b."""
    return [-cc.ma * dx, cc.mb * dx, -cc.ma * dy, cc.mb * dy,
            -cc.ia * cross(cc.rax[:, k], cc.ray[:, k], dx, dy), cc.ib * cross(cc.rbx[:, k], cc.rby[:, k], dx, dy)]


def pack_constraints(layout: ContactLayout, cc: ContactConstraints) -> jax.Array:
    per_point = (cc.rax, cc.ray, cc.rbx, cc.rby, cc.normal_mass, cc.tangent_mass, cc.relative_velocity,
                 cc.impact_boost, cc.mass_scale, cc.stiff)
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


def warm_start(layout: ContactLayout, const, impulses, vel: Vel, plan: Schedule) -> Vel:
    """Re-apply the accumulated impulses before solving.

    A sweep over the colours rather than one scatter-add: the sum on each body then
    always runs in colour order (the same for every batch width and every run of a program).
    """

    def apply_colour(vels, lam, points, c: Block):
        for row, (kind, k) in ((NORMAL, ("normal", 0)), (NORMAL + 1, ("normal", 1)), (TANGENT, ("tangent", 0)),
                               (TANGENT + 1, ("tangent", 1))):
            vels = vels + c.push(kind, k) * lam[row][None]
        return vels, None

    return sweep(layout, vel, apply_colour, const, impulses, plan)[0]


def solve(layout: ContactLayout, const, impulses, vel: Vel, separation, softness: Softness, inv_h, max_push,
          use_bias: bool, plan: Schedule | Chain) -> tuple[Vel, jax.Array]:
    """One Gauss-Seidel sweep of normal then friction constraints over the plan's colours.

    const: packed constraints; impulses: packed (C, 6, K); separation: packed (C, 2, K).
    softness: the scene's (its bias rate; each point's mass scale is its "soft" row, load_softness).
    A Chain plan (sweeps.chain of the live colours and schedule(const, rows="stiff")) follows the pass over all
    colours with extra passes over the points load_softness stiffened (one loop after it): in its passes 1, 2, ...
    only those points are solved (the others keep their impulses), and the odd ones take each manifold's second
    point first.
    """

    def normal(c: Block, sep, stiff_only, k, vels, lam):
        vn = velocity_along(c, k, vels, c.nx, c.ny)
        s = sep[k]
        speculative = s > 0.0
        if use_bias:
            soft_scale = c.point("soft", k)
            bias = jnp.where(speculative, s * inv_h, jnp.maximum(softness.bias_rate * s, -max_push))
            mass_scale = jnp.where(speculative, 1.0, soft_scale)
            impulse_scale = jnp.where(speculative, 0.0, 1.0 - soft_scale)
        else:
            bias = jnp.where(speculative, s * inv_h, 0.0)
            mass_scale, impulse_scale = 1.0, 0.0
        old = lam[NORMAL + k]
        new = jnp.maximum(old - c.point("nmass", k) * mass_scale * (vn + bias) - impulse_scale * old, 0.0)
        return keep(c, stiff_only, k, old, new)

    def friction(c: Block, stiff_only, k, vels, lam):
        vt = velocity_along(c, k, vels, c.ny, -c.nx)
        old = lam[TANGENT + k]
        limit = c.friction * lam[NORMAL + k]
        return keep(c, stiff_only, k, old, jnp.clip(old - c.point("tmass", k) * vt, -limit, limit))

    def keep(c: Block, stiff_only: bool, k, old, new):
        return jnp.where(c.point("stiff", k) > 0.0, new, old) if stiff_only else new

    def solve_colour(vels, lam, points, c: Block, sep: Rows, pass_of: int = 0):
        stiff_only, reverse = pass_of > 0, pass_of % 2 == 1  # a Chain's repeats (sweeps.sweep)
        rows = (ImpulseRow(NORMAL, functools.partial(normal, c, sep, stiff_only),
                           functools.partial(apply_impulse, c, "normal", NORMAL, track_max=True)),
                ImpulseRow(TANGENT, functools.partial(friction, c, stiff_only),
                           functools.partial(apply_impulse, c, "tangent", TANGENT)))
        return for_points(points, rows, vels, lam, reverse)

    return sweep(layout, vel, solve_colour, const, impulses, plan, separation)
