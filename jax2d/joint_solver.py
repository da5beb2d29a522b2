"""Joint constraints: revolute (point + optional motor and limits) and fixed (weld).

Soft constraints as in Box2D v3's soft step. Joints connect bodies chosen by the
level (data, not constants): impulses reach the bodies through one-hot rows
(J, M) built once per step, and the solve loop reads a joint's two bodies by a
gather by body index (see _ends).
Joints are solved one after another (Gauss-Seidel) in a loop, which keeps chains
stiff; at the end of each step `project` solves all joints at once (joint_block), which
holds where a few sweeps do not converge (a light body carrying several joints).
Everything here runs on batch-last arrays (step.py): per body (M, *batch), per joint
(J, *batch), one-hot rows (J, M, *batch).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jax2d import joint_block
from jax2d.math2d import (
    Pose,
    Softness,
    Vel,
    at,
    cross,
    one_hot_rows,
    ordered_sum,
    pick_rows_each,
    rotate,
    safe_inverse,
    set_at,
    stored,
)
from jax2d.state import J_ANGULAR, J_LINEAR_X, J_LINEAR_Y, J_LOWER, J_MOTOR, J_UPPER, Joints

# The soft rows close a joint's position error at most this fast (m/s; rad/s for a weld's angle). Errors up to
# 8 cm (0.08 rad) close at the soft rate as before (bias rate 127 /s at 60 Hz and 4 substeps); a joint torn wider
# closes over a few steps. Without the cap a torn joint's bias ran away: in crowded scenes 329, 385, 441 and 509
# of tests/jax2d/accuracy.py a light hub's welds were pushed apart by deep spawn overlaps, their bias (127 /s
# times the error) threw bodies at the speed clamp, the errors grew, and 20-500 steps later the impulses
# overflowed and the NaN guard froze the scene (see docs/engine.md, "Torn joints").
MAX_CLOSING_SPEED = 10.0


class JointConstraints(NamedTuple):
    sel_a: jax.Array  # (J, M) one-hot row of body a, zero for inactive joints
    sel_b: jax.Array
    body_a: jax.Array  # (J,) int32 body indices, for joint_block's "same body" test
    body_b: jax.Array
    rows: jax.Array  # (3J,) joint_block.row_mask
    ma: jax.Array  # (J,) inverse masses / inertias
    ia: jax.Array
    mb: jax.Array
    ib: jax.Array
    axial_mass: jax.Array  # (J,) 1 / (ia + ib)
    revolute: jax.Array  # (J,) float 1/0 masks
    weld: jax.Array
    motor: jax.Array
    limit: jax.Array
    motor_target: jax.Array  # (J,) relative angular velocity the motor drives to
    max_motor_impulse: jax.Array  # (J,) per substep
    lower: jax.Array  # (J,) angle limits
    upper: jax.Array


class JointFrame(NamedTuple):
    """Joint geometry at the current substep."""

    rax: jax.Array  # (J,) anchor offsets from the centres of mass, world orientation
    ray: jax.Array
    rbx: jax.Array
    rby: jax.Array
    cx: jax.Array  # (J,) position error (anchor b - anchor a)
    cy: jax.Array
    angle: jax.Array  # (J,) angle_b - angle_a - ref_angle


def prepare(joints: Joints, num_padded: int, inv_mass, inv_inertia, motor_actions, h, params) -> JointConstraints:
    """Constraints for one step, on batch-last arrays like the rest (step._prepare)."""
    active = joints.active.astype(jnp.float32)
    sel_a = one_hot_rows(joints.a, num_padded) * active[:, None]
    sel_b = one_hot_rows(joints.b, num_padded) * active[:, None]
    ma, ia = pick_rows_each(sel_a, inv_mass, inv_inertia)
    mb, ib = pick_rows_each(sel_b, inv_mass, inv_inertia)
    axial = safe_inverse(ia + ib)
    revolute = active * (~joints.fixed)
    weld = active * joints.fixed
    motor = revolute * joints.motor_on
    action = jnp.clip(motor_actions, -1.0, 1.0)
    return JointConstraints(
        sel_a=sel_a, sel_b=sel_b, body_a=joints.a, body_b=joints.b,
        rows=joint_block.row_mask(active, weld),
        ma=ma, ia=ia, mb=mb, ib=ib,
        axial_mass=axial,
        revolute=revolute, weld=weld, motor=motor,
        limit=revolute * joints.limit_on,
        motor_target=joints.motor_speed * params.base_motor_speed * action,
        max_motor_impulse=motor * jnp.abs(joints.motor_power) * params.base_motor_power * axial * h,
        lower=joints.lower,
        upper=joints.upper,
    )


def frame(joints: Joints, jc: JointConstraints, pose: Pose) -> JointFrame:
    ax, ay, aa = pick_rows_each(jc.sel_a, pose.x, pose.y, pose.a)
    bx, by, ab = pick_rows_each(jc.sel_b, pose.x, pose.y, pose.a)
    rax, ray = rotate(jnp.cos(aa), jnp.sin(aa), joints.anchor_a[:, 0], joints.anchor_a[:, 1])
    rbx, rby = rotate(jnp.cos(ab), jnp.sin(ab), joints.anchor_b[:, 0], joints.anchor_b[:, 1])
    cx = (bx + rbx) - (ax + rax)
    cy = (by + rby) - (ay + ray)
    # Only active rows are meaningful; inactive ones have zero selections and masses.
    # A revolute joint's angle counts turns (its limits may span more than a half turn); a weld is back in place
    # after a whole turn, so its error is the nearest angle to the rest one, in [-pi, pi].
    angle = ab - aa - joints.ref_angle
    angle = jnp.where(jc.weld > 0, angle - 2.0 * jnp.pi * jnp.round(angle * (0.5 / jnp.pi)), angle)
    return JointFrame(rax, ray, rbx, rby, cx, cy, angle)


class Schedule(NamedTuple):
    """Which joint slots the loops visit: the first `count` entries of `order`, in slot order. A fixed one
    (jax2d/control.py) visits every slot: order is 0..J-1 and count J, a Python int."""

    order: jax.Array  # (J,) int32: the live slots first (ascending), then the others
    count: jax.Array | int  # () int32; an int in a fixed schedule

    @property
    def fixed(self) -> bool:
        return isinstance(self.count, int)


def schedule(jc: JointConstraints, fixed: bool = False) -> Schedule:
    """The joint slots active in any scene of the batch (jc batch-last); with `fixed`, every slot.

    An inactive slot has zero selections, masses and impulses, so solving it changes
    nothing; the loops skip it (levels rarely fill their joint capacity).
    """
    if fixed:
        return Schedule(jnp.arange(jc.revolute.shape[0], dtype=jnp.int32), jc.revolute.shape[0])
    active = jc.revolute + jc.weld
    live = jnp.any(active > 0.0, axis=tuple(range(1, active.ndim)))
    return Schedule(jnp.argsort(~live, stable=True).astype(jnp.int32), jnp.sum(live, dtype=jnp.int32))


def _visited(plan: Schedule, i):
    """The joint slot a loop visits in its i-th iteration."""
    return i if plan.fixed else at(plan.order, i)


def warm_start(jc: JointConstraints, fr: JointFrame, impulse, vel: Vel, plan: Schedule) -> Vel:
    """Re-apply every joint's accumulated impulses before solving, joint by joint (a fixed order
    of additions, the same for every batch width)."""
    if impulse.shape[0] == 0:
        return vel

    def one_joint(j, v):
        lam = at(impulse, j)
        px, py = lam[J_LINEAR_X], lam[J_LINEAR_Y]
        turn = lam[J_MOTOR] + lam[J_LOWER] - lam[J_UPPER] + lam[J_ANGULAR]
        ta = -at(jc.ia, j) * (cross(at(fr.rax, j), at(fr.ray, j), px, py) + turn)
        tb = at(jc.ib, j) * (cross(at(fr.rbx, j), at(fr.rby, j), px, py) + turn)
        return _add_at_ends(v, at(jc.sel_a, j), at(jc.sel_b, j), (-(at(jc.ma, j) * px), -(at(jc.ma, j) * py), ta),
                            (at(jc.mb, j) * px, at(jc.mb, j) * py, tb))

    v = jax.lax.fori_loop(0, plan.count, lambda i, v: one_joint(_visited(plan, i), v), jnp.stack(vel))
    return Vel(v[0], v[1], v[2])


def _ends(jc: JointConstraints, j, v) -> jax.Array:
    """(2, 3, *batch) the velocities (x, y, w) of joint j's bodies a and b, zero for an inactive joint.

    A gather by body index: the masked sum over the bodies' one-hot rows, as one reduction,
    compiled to a library kernel that took 50 us per joint at a batch of 256.
    """
    index = jnp.stack([at(jc.body_a, j), at(jc.body_b, j)])  # (2, *batch)
    index = index.reshape((2, 1, 1) + index.shape[1:])
    picked = jnp.take_along_axis(v[None], index, axis=2, mode="clip")[:, :, 0]
    return jnp.where(at(jc.revolute, j) + at(jc.weld, j) > 0, picked, 0.0)


def _add_at_ends(v, sa, sb, on_a, on_b):
    """v (3, M, *batch) stacked velocities plus (x, y, w) changes on_a at the body sa selects and on_b at sb's.

    The loops carry the velocities as one array so that each joint's update is one kernel, not three.
    """
    return jnp.stack([v[k] + sa * on_a[k] + sb * on_b[k] for k in range(3)])


def _closing(bias):
    """A bias velocity, at most MAX_CLOSING_SPEED either way."""
    return jnp.clip(bias, -MAX_CLOSING_SPEED, MAX_CLOSING_SPEED)


def _soft_terms(c, softness: Softness, inv_h, use_bias: bool, speculative: bool):
    """(bias, mass scale, impulse scale) for a position error c."""
    if speculative:  # inequality constraints: approach a separated limit exactly
        ahead = c > 0.0
        if use_bias:
            return (jnp.where(ahead, c * inv_h, _closing(softness.bias_rate * c)),
                    jnp.where(ahead, 1.0, softness.mass_scale), jnp.where(ahead, 0.0, softness.impulse_scale))
        return jnp.where(ahead, c * inv_h, 0.0), 1.0, 0.0
    if use_bias:
        return _closing(softness.bias_rate * c), softness.mass_scale, softness.impulse_scale
    return 0.0, 1.0, 0.0


def solve(jc: JointConstraints, fr: JointFrame, impulse, vel: Vel, softness: Softness, inv_h,
          use_bias: bool, plan: Schedule) -> tuple[Vel, jax.Array]:
    """One Gauss-Seidel pass over the live joints (see schedule; a loop, so it compiles once):
    motor, limits, then point / weld."""
    if impulse.shape[0] == 0:
        return vel, impulse

    def angular(j, impulse, ends):
        """Motor, then the two angle limits: new (motor, lower, upper) impulses and angular velocities."""
        lam, wa, wb = at(impulse, j), ends[0, 2], ends[1, 2]
        ia, ib, axial, angle = at(jc.ia, j), at(jc.ib, j), at(jc.axial_mass, j), at(fr.angle, j)
        # Motor: drive the relative angular velocity to the target, with bounded torque.
        limit = at(jc.max_motor_impulse, j)
        motor = lam[J_MOTOR] + at(jc.motor, j) * (
            jnp.clip(lam[J_MOTOR] - axial * (wb - wa - at(jc.motor_target, j)), -limit, limit) - lam[J_MOTOR])
        d = motor - lam[J_MOTOR]
        wa, wb = wa - ia * d, wb + ib * d
        # Limits: one-sided constraints on the relative angle (lower: angle >= lower, upper: angle <= upper).
        limits = []
        for col, gap, sign in ((J_LOWER, angle - at(jc.lower, j), 1.0), (J_UPPER, at(jc.upper, j) - angle, -1.0)):
            bias, ms, isc = _soft_terms(gap, softness, inv_h, use_bias, speculative=True)
            old = lam[col]
            new = jnp.maximum(old - axial * ms * (sign * (wb - wa) + bias) - isc * old, 0.0)
            d = (new - old) * at(jc.limit, j)
            limits.append(old + d)
            wa, wb = wa - sign * ia * d, wb + sign * ib * d
        return motor, limits[0], limits[1], wa, wb

    def point(j, impulse, ends, wa, wb):
        """Point (revolute) or point + angle (weld) impulse (px, py, pw), as one block solve so the
        linear and angular parts do not fight each other (solving them one after the other rings
        and, with warm starting, grew without bound on a spinning welded cluster)."""
        lam, (vax, vay, _), (vbx, vby, _) = at(impulse, j), ends[0], ends[1]
        ma, ia, mb, ib = at(jc.ma, j), at(jc.ia, j), at(jc.mb, j), at(jc.ib, j)
        rax, ray, rbx, rby = at(fr.rax, j), at(fr.ray, j), at(fr.rbx, j), at(fr.rby, j)
        cdx = (vbx - wb * rby) - (vax - wa * ray)
        cdy = (vby + wb * rbx) - (vay + wa * rax)
        cdw = wb - wa
        bx, ms, isc = _soft_terms(at(fr.cx, j), softness, inv_h, use_bias, speculative=False)
        by, _, _ = _soft_terms(at(fr.cy, j), softness, inv_h, use_bias, speculative=False)
        bw, _, _ = _soft_terms(at(fr.angle, j), softness, inv_h, use_bias, speculative=False)
        k11 = ma + mb + ray * ray * ia + rby * rby * ib
        k12 = -ray * rax * ia - rby * rbx * ib
        k22 = ma + mb + rax * rax * ia + rbx * rbx * ib
        k13 = -ray * ia - rby * ib
        k23 = rax * ia + rbx * ib
        k33 = ia + ib
        rx, ry, rw = cdx + bx, cdy + by, cdw + bw
        ox, oy, ow = lam[J_LINEAR_X], lam[J_LINEAR_Y], lam[J_ANGULAR]
        # Revolute: 2x2.
        inv2 = safe_inverse(k11 * k22 - k12 * k12)
        px2 = inv2 * (k22 * rx - k12 * ry)
        py2 = inv2 * (k11 * ry - k12 * rx)
        # Weld: 3x3 by cofactors (K is symmetric).
        c11, c12, c13 = k22 * k33 - k23 * k23, k13 * k23 - k12 * k33, k12 * k23 - k13 * k22
        c22, c23, c33 = k11 * k33 - k13 * k13, k12 * k13 - k11 * k23, k11 * k22 - k12 * k12
        inv3 = safe_inverse(k11 * c11 + k12 * c12 + k13 * c13)
        px3 = inv3 * (c11 * rx + c12 * ry + c13 * rw)
        py3 = inv3 * (c12 * rx + c22 * ry + c23 * rw)
        pw3 = inv3 * (c13 * rx + c23 * ry + c33 * rw)
        weld = at(jc.weld, j) > 0
        px = -ms * jnp.where(weld, px3, px2) - isc * ox
        py = -ms * jnp.where(weld, py3, py2) - isc * oy
        pw = jnp.where(weld, -ms * pw3 - isc * ow, 0.0)
        return px, py, pw

    def one_joint(j, carry):
        v, impulse = carry
        lam = at(impulse, j)
        sa, sb = at(jc.sel_a, j), at(jc.sel_b, j)
        # Both ends' velocities in one kernel: (2, 3, *batch). The stages below take it whole and the
        # joint's impulses as the whole array: a conditional's operands are buffers, and a slice of
        # each would be a kernel of its own.
        ends = _ends(jc, j, v)
        wa0, wb0 = ends[0, 2], ends[1, 2]
        # Each stage's results are stored (see math2d.stored) before the next reads them.
        token = None if plan.fixed else j  # math2d.stored
        motor, lower, upper, wa, wb = stored(token, angular, j, impulse, ends)
        px, py, pw = stored(token, point, j, impulse, ends, wa, wb)
        ma, ia, mb, ib = at(jc.ma, j), at(jc.ia, j), at(jc.mb, j), at(jc.ib, j)
        dwa = wa - wa0 - ia * (cross(at(fr.rax, j), at(fr.ray, j), px, py) + pw)
        dwb = wb - wb0 + ib * (cross(at(fr.rbx, j), at(fr.rby, j), px, py) + pw)

        columns = [None] * 6
        columns[J_LINEAR_X], columns[J_LINEAR_Y] = lam[J_LINEAR_X] + px, lam[J_LINEAR_Y] + py
        columns[J_ANGULAR], columns[J_MOTOR] = lam[J_ANGULAR] + pw, motor
        columns[J_LOWER], columns[J_UPPER] = lower, upper
        impulse = set_at(impulse, j, jnp.stack(columns))
        return _add_at_ends(v, sa, sb, (-(ma * px), -(ma * py), dwa), (mb * px, mb * py, dwb)), impulse

    v, impulse = jax.lax.fori_loop(0, plan.count, lambda i, carry: one_joint(_visited(plan, i), carry),
                                   (jnp.stack(vel), impulse))
    return Vel(v[0], v[1], v[2]), impulse


def project(jc: JointConstraints, fr: JointFrame, vel: Vel, bias_rate, plan: Schedule,
            position_fraction: float | None = None) -> tuple[Vel, Pose | None]:
    """The joint projection stage at the end of a step: all joints' point and weld rows at once (joint_block).

    Velocities: made to satisfy every row exactly, plus `bias_rate` times each row's position
    error. Positions (when `position_fraction` is given): the displacement of least kinetic metric
    that removes that fraction of every row's error, to first order; per body at most
    MAX_SHIFT and MAX_TURN, so a joint far apart closes over several steps instead of jumping.
    The displacement leaves velocities alone (no energy is added), and neither part's impulses are
    kept for warm starting. Returns the velocities and the displacement (None without positions).
    """
    if jc.rows.shape[0] == 0:
        return vel, None if position_fraction is None else Pose(0.0, 0.0, 0.0)
    a = joint_block.matrix(((jc.body_a, jc.ma, jc.ia, fr.rax, fr.ray), (jc.body_b, jc.mb, jc.ib, fr.rbx, fr.rby)),
                           jc.rows)
    vax, vay, wa = pick_rows_each(jc.sel_a, vel.x, vel.y, vel.w)
    vbx, vby, wb = pick_rows_each(jc.sel_b, vel.x, vel.y, vel.w)
    error = jnp.stack([fr.cx, fr.cy, fr.angle], axis=1)  # (J, 3, *batch)
    rows = jc.rows.reshape(error.shape)
    velocity_rhs = jnp.stack([(vbx - wb * fr.rby) - (vax - wa * fr.ray), (vby + wb * fr.rbx) - (vay + wa * fr.rax),
                              wb - wa], axis=1) + _closing(bias_rate * error)
    rhs = (velocity_rhs,) if position_fraction is None else (velocity_rhs, position_fraction * _beyond_slop(fr))
    lams = joint_block.solve(a, tuple((r * rows).reshape(jc.rows.shape) for r in rhs), plan.order, plan.count)
    dvx, dvy, dw = _spread_rows(jc, fr, lams[0].reshape(error.shape) * rows)
    vel = Vel(vel.x + dvx, vel.y + dvy, vel.w + dw)
    if position_fraction is None:
        return vel, None
    dx, dy, da = _spread_rows(jc, fr, lams[1].reshape(error.shape) * rows)
    scale = jnp.minimum(1.0, MAX_SHIFT / jnp.maximum(jnp.sqrt(dx * dx + dy * dy), 1e-9))
    return vel, Pose(dx * scale, dy * scale, jnp.clip(da, -MAX_TURN, MAX_TURN))


# Largest displacement per body and step of the position projection. Its first-order step
# overshoots where a correction turns a body far (the anchors move on arcs, not lines), and
# repeated overshoots grew into an explosion in one crowded scene out of 64 x 8 action streams;
# with these caps none did (docs/engine.md). Larger errors close over several steps.
MAX_SHIFT = 0.1  # m
MAX_TURN = 0.15  # rad
# Errors up to these are left to the soft rows (see _beyond_slop).
POSITION_SLOP = 0.001  # m
ANGLE_SLOP = 0.005  # rad


def _beyond_slop(fr: JointFrame) -> jax.Array:
    """(J, 3, *batch) the part of each joint's position error beyond POSITION_SLOP / ANGLE_SLOP.

    The small errors every step leaves (anchors move on arcs, the integration on lines) are the soft
    rows' to correct, with impulses, which keep momentum: a displacement changes no velocity, so
    pulling a spinning welded star's arms in by it slowed the star (3.4 % in 5 s).
    """
    length = jnp.sqrt(fr.cx * fr.cx + fr.cy * fr.cy)
    keep = jnp.maximum(length - POSITION_SLOP, 0.0) / jnp.maximum(length, POSITION_SLOP)
    angle = jnp.sign(fr.angle) * jnp.maximum(jnp.abs(fr.angle) - ANGLE_SLOP, 0.0)
    return jnp.stack([fr.cx * keep, fr.cy * keep, angle], axis=1)


def _spread_rows(jc: JointConstraints, fr: JointFrame, lam) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Per body (M, *batch) x, y and angle changes from multipliers lam (J, 3, *batch) with A lam = r
    (joint_block.solve): the change -M^-1 J^T lam removes the rows' values r, to first order."""
    # A scene whose system could not be solved (non-finite input) is left as it is.
    lam = jnp.where(jnp.isfinite(lam), -lam, 0.0)
    px, py, pw = lam[:, 0], lam[:, 1], lam[:, 2]
    twist_a = -jc.ia * (cross(fr.rax, fr.ray, px, py) + pw)
    twist_b = jc.ib * (cross(fr.rbx, fr.rby, px, py) + pw)

    def spread(on_a, on_b):  # (J, *batch) per joint end -> (M, *batch) per body
        # in joint order (math2d.ordered_sum): a body on several joints gets the same bits at every batch width
        return ordered_sum(jc.sel_a * on_a[:, None] + jc.sel_b * on_b[:, None], axis=0)

    return spread(-jc.ma * px, jc.mb * px), spread(-jc.ma * py, jc.mb * py), spread(twist_a, twist_b)
