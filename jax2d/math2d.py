"""Small 2D helpers shared by the solver stages, written on separate x / y arrays.

The solver keeps every body quantity as its own 1-D array (structure of arrays):
under `vmap` that puts the batch in a contiguous axis of every operand, which
measured 4-7x faster on the CPU than (N, 2) / (N, 3) arrays of structs.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


class Vel(NamedTuple):
    """Body velocities, one entry per padded body."""

    x: jax.Array
    y: jax.Array
    w: jax.Array


class Pose(NamedTuple):
    """Body positions and angles, one entry per padded body."""

    x: jax.Array
    y: jax.Array
    a: jax.Array


def cross(ax, ay, bx, by):
    """z component of a x b."""
    return ax * by - ay * bx


def rotate(c, s, x, y):
    """Rotate (x, y) by the angle whose cosine and sine are (c, s)."""
    return c * x - s * y, s * x + c * y


def pick_rows(sel, x):
    """x at the body each one-hot row selects: sel (R, M, *batch), x (M, *batch) -> (R, *batch).

    A masked sum rather than `sel @ x` so it also works on batch-last arrays (step.py). Only one
    term of each row is non-zero, so the result is exact.
    """
    return jnp.sum(sel * x[None], axis=1)


def one_hot_rows(index, m: int):
    """index (R, *batch) int -> (R, m, *batch) float32 one-hot rows (all zero for an index outside [0, m)).

    jax.nn.one_hot puts the classes last; the solver wants them before trailing batch axes.
    """
    classes = jnp.arange(m).reshape((1, m) + (1,) * (index.ndim - 1))
    return (index[:, None] == classes).astype(jnp.float32)


def at(x, i):
    """x[i] on axis 0 for a traced loop index i that is in range.

    `x[i]` with a traced i also wraps negative indices around, and inside the solver's loops that
    select is a kernel of its own in every iteration; a loop index is never negative.
    """
    return jax.lax.dynamic_index_in_dim(x, i, 0, keepdims=False, allow_negative_indices=False)


def set_at(x, i, value):
    """x.at[i].set(value) for a traced loop index i that is in range (see `at`): a plain update
    in place, without the wrap-around and the bounds check of a scatter."""
    return jax.lax.dynamic_update_index_in_dim(x, value, i, 0, allow_negative_indices=False)


def stored(token, fn, *args):
    """fn(*args), computed once and kept in memory for every consumer.

    XLA's CPU fusion copies a chain of elementwise operations into each of its consumers, so
    an impulse read by six velocity updates was computed six times (and a chain of such
    stages multiplies). `lax.optimization_barrier` does not stop it: the CPU pipeline removes
    barriers before fusing. A conditional's branch is a computation of its own, so its
    results are stored. `token` is a traced non-negative integer (a loop index): the
    condition is always true, but XLA cannot know that and keeps the conditional.
    """

    def zeros(*a):
        return jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(fn, *a))

    return jax.lax.cond(token >= 0, fn, zeros, *args)


def safe_inverse(x):
    """1 / x, and 0 where x is 0 (a constraint between two static bodies)."""
    nonzero = x > 0.0
    return jnp.where(nonzero, 1.0 / jnp.where(nonzero, x, 1.0), 0.0)


class Softness(NamedTuple):
    """A soft constraint as a (bias rate, mass scale, impulse scale) triple."""

    bias_rate: jax.Array
    mass_scale: jax.Array
    impulse_scale: jax.Array


def soft(hertz, damping_ratio, h) -> Softness:
    """Soft constraint coefficients for an implicit spring-damper (Catto, "Solver2D", 2024).

    A constraint with stiffness `hertz` and `damping_ratio`, integrated implicitly over
    a substep `h`, becomes: impulse = -mass * mass_scale * (Cdot + bias_rate * C)
    - impulse_scale * accumulated_impulse.
    """
    omega = 2.0 * jnp.pi * hertz
    a1 = 2.0 * damping_ratio + h * omega
    a2 = h * omega * a1
    a3 = 1.0 / (1.0 + a2)
    return Softness(omega / a1, a2 * a3, a3)
