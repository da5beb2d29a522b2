"""Restitution: the bounce stage after the substeps, in two passes over the contact colours.

The substeps solve every contact as inelastic (with a soft position bias). A bounce then needs
each touching point's separating velocity, and a single target per point, e times the point's
approach speed before solving, is wrong for chains of touching bodies: in a Newton's cradle the
balls at rest touch with an approach speed of 0, so they stayed together and the chain lost 16 %
of its energy (ending at (-0.60, 1.19, 2.40) instead of (0, 0, 3)).

1. Impact propagation, on the velocities from before the step: Gauss-Seidel sweeps over the
   colours in which every point with restitution e > 0 that approaches faster than the threshold
   (and was pushed by the solver this step, so it really touched) takes the impulse of a two-body
   collision, -(1 + e) m_n v_n, from its approach speed at that moment. An impact so travels
   through a chain of touching bodies as it does in a sequence of pairwise collisions (the
   cradle's first ball stops, the second receives 3 m/s and passes it on to the third). Each point's
   normal velocity at the end is its target separating speed; a point that took no propagation
   impulse has target 0. Points with e = 0 take no part: a bouncing ball on a box resting on a
   dead floor then bounces as from the floor (the floor contact stays rigid in pass 2), instead
   of the box absorbing the impact.
2. Bounce, on the solved velocities: Gauss-Seidel sweeps in which every point pushed this step,
   in a scene where some point bounces, drives its normal velocity to at least its target with
   the accumulated normal impulse kept non-negative (as Box2D's restitution, with these targets).

A scene where nothing bounces is left alone, so its result does not depend on the other scenes
of the batch; a batch where nothing bounces skips the stage.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from jax2d.control import if_any
from jax2d.math2d import Vel
from jax2d.pairs import ContactLayout
from jax2d.sweeps import (
    MAX,
    NORMAL,
    ROW,
    Block,
    ImpulseRow,
    Rows,
    Schedule,
    apply_impulse,
    for_points,
    sweep,
    velocity_along,
    with_rows,
)

# Rows of the propagation pass's packed (C, 6, K, *batch) array.
_KICK = 0  # rows 0-1: the propagation impulse taken by point 0 / 1
_END = 2  # rows 2-3: its normal velocity at the end of the propagation
_GAP = 4  # rows 4-5: its separation at the end of the step


def restitution(layout: ContactLayout, const, impulses, vel: Vel, vel0: Vel, gap, h, threshold, plan: Schedule,
                impact_sweeps: int, bounce_sweeps: int) -> tuple[Vel, jax.Array]:
    """The bounce stage (module docstring). vel: the solved velocities; vel0: those from before the step;
    const, impulses: the packed contact constraints and the step's accumulated impulses (contact_solver);
    gap: a function giving (C, 2, K, *batch) each point's separation at the step's end (called only where
    something bounces);
    h: the substep."""
    rel = const[:, ROW["rel0"]:ROW["rel0"] + 2] + const[:, ROW["boost0"]:ROW["boost0"] + 2]
    pushed = impulses[:, MAX:MAX + 2] > 0.0
    bouncy = const[:, None, ROW["restitution"]] > 0.0
    hit = (rel < -threshold) & pushed & bouncy  # (C, 2, K, *batch)
    scene_bounces = jnp.any(hit, axis=(0, 1, 2))  # (*batch)

    def approach(c: Block, k, vels):
        """A point's normal velocity in the propagation, with the speed it gains under gravity before impact."""
        return velocity_along(c, k, vels, c.nx, c.ny) + c.point("boost", k)

    def propagate(c: Block, main: Rows, k, vels, lam):
        vn = approach(c, k, vels)
        kick = (vn < -threshold) & (main[MAX + k] > 0.0) & (c.restitution > 0.0)
        return lam[_KICK + k] + jnp.where(kick, -(1.0 + c.restitution) * c.point("nmass", k) * vn, 0.0)

    def propagate_colour(vels, lam, points, c: Block, main: Rows):
        return for_points(points, (ImpulseRow(_KICK, functools.partial(propagate, c, main),
                                              functools.partial(apply_impulse, c, "normal", _KICK)),), vels, lam)

    def measure_colour(vels, lam, points, c: Block):
        return vels, with_rows(lam, [(_END + k, approach(c, k, vels)) for k in range(2)])

    def bounce(c: Block, prop: Rows, k, vels, lam):
        # The propagation ends at the separating speed right after impact. The velocity the step stores is
        # the mean over a substep of flight, so it is lifted by -g_n h / 2 (contact_solver.prepare's impact_boost):
        # without the lift a bounce's apex came out g h / v low, 4 % of a 6 cm bounce at 4 substeps.
        out = jnp.maximum(prop[_END + k], 0.0)
        # A point still apart at the step's end (a speculative contact, pushed so that it does not cross
        # in the next substep) bounces early, from the height of its gap: launched at the impact's
        # speed it rose that much too high (3.4 mm of a 6 cm bounce). It leaves with the speed it would
        # have there after a bounce at contact, sqrt(out^2 + 2 g_n gap).
        out = jnp.sqrt(jnp.maximum(out * out + 2.0 * c.gn * jnp.maximum(prop[_GAP + k], 0.0), 0.0))
        target = jnp.where(prop[_KICK + k] > 0.0, out - 0.5 * h * c.gn, 0.0)
        vn = velocity_along(c, k, vels, c.nx, c.ny)
        old = lam[NORMAL + k]
        new = jnp.maximum(old - c.point("nmass", k) * (vn - target), 0.0)
        return jnp.where(scene_bounces & (lam[MAX + k] > 0.0), new, old)

    def bounce_colour(vels, lam, points, c: Block, prop: Rows):
        return for_points(points, (ImpulseRow(NORMAL, functools.partial(bounce, c, prop),
                                              functools.partial(apply_impulse, c, "normal", NORMAL)),), vels, lam)

    def run():
        prop = jnp.zeros_like(impulses)
        v = vel0
        for _ in range(impact_sweeps):
            v, prop = sweep(layout, v, propagate_colour, const, prop, plan, impulses)
        _, prop = sweep(layout, v, measure_colour, const, prop, plan)
        prop = prop.at[:, _GAP:_GAP + 2].set(gap())
        v, lam = vel, impulses
        for _ in range(bounce_sweeps):
            v, lam = sweep(layout, v, bounce_colour, const, lam, plan, prop)
        return v, lam

    # Most steps bounce nowhere in the batch; the stage would then change nothing, so it is skipped:
    # a few hundred small kernels per sweep at a small batch (run always with fixed control flow, control.py).
    return if_any(plan.fixed, scene_bounces, run, lambda: (vel, impulses))
