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


def rotation(angle) -> jax.Array:
    """(2, *angle.shape) the cosine and sine of `angle`, stacked (to be computed once, math2d.stored)."""
    return jnp.stack([jnp.cos(angle), jnp.sin(angle)])


def rotate(c, s, x, y):
    """Rotate (x, y) by the angle whose cosine and sine are (c, s)."""
    return c * x - s * y, s * x + c * y


def pick_rows(sel, x):
    """x at the body each one-hot row selects: sel (R, M, *batch), x (M, *batch) -> (R, *batch).

    A masked sum rather than `sel @ x` so it also works on batch-last arrays (step.py). Only one
    term of each row is non-zero, so the result is exact.
    """
    return jnp.sum(sel * x[None], axis=1)


def picked(mask, axis: int, *values) -> tuple[jax.Array, ...]:
    """Each of `values` summed over `axis` where `mask` is true, as one reduction: with a mask that selects one
    element (or none) along the axis, the value there (or 0), exactly. XLA's CPU runtime pays about half a
    microsecond per call for every reduction in a program, run or not (docs/engine.md, "Reductions cost per
    call"), so sums over the same mask are stacked."""
    shape = jnp.broadcast_shapes(mask.shape, *(jnp.shape(v) for v in values))
    stacked = jnp.stack([jnp.broadcast_to(v, shape) for v in values])
    return tuple(jnp.sum(jnp.where(mask[None], stacked, 0.0), axis=axis + 1 if axis >= 0 else axis))


def pick_rows_each(sel, *xs) -> tuple[jax.Array, ...]:
    """pick_rows(sel, x) for each of xs; the same bits either way.

    For a single scene (batch axis of 1) as one reduction: XLA's CPU runtime pays per call for every reduction in
    a program, and at batch 1 that per-call cost is what a step costs (docs/engine.md, "Reductions cost per
    call"). On a batch, one reduction each: the stacked product made the engine 8 % slower at s 256."""
    if sel.shape[-1] != 1:
        return tuple(pick_rows(sel, x) for x in xs)
    return tuple(jnp.sum(sel[None] * jnp.stack(xs)[:, None], axis=2))


def ordered_sum(x, axis: int = 0):
    """x summed over `axis` in index order, as a chain of elementwise adds: the same bits at every batch width.

    XLA's CPU reduce (jnp.sum) accumulates in an order that depends on the array's whole shape: summing
    one scene's terms over a joint axis gave results 1 ulp apart when the scene was stepped in a batch of
    8 or of 16 (issue 33), and a chaotic scene (levels/cartpole.json) grows that to O(1) in 64 steps, so a
    run split over devices or processes diverged from the same run on one. Elementwise adds have no such
    freedom. For the short axes of the joint projection (3 x joints at most); an empty axis sums to 0.
    """
    x = jnp.moveaxis(x, axis, 0)
    if x.shape[0] == 0:
        return jnp.zeros(x.shape[1:], x.dtype)
    total = x[0]
    for k in range(1, x.shape[0]):
        total = total + x[k]
    return total


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
    condition is always true, but XLA cannot know that and keeps the conditional. A constant
    token (jnp.int32(0)) is folded away with the conditional, and the result fused again.
    token None: plainly fn(*args), for fixed control flow (jax2d/control.py), where a GPU would
    wait on the host for every conditional.
    """
    if token is None:
        return fn(*args)
    shapes = jax.eval_shape(fn, *args)
    leaves, tree = jax.tree.flatten(shapes)
    if len(leaves) > 1 and len({(leaf.shape, leaf.dtype) for leaf in leaves}) == 1:
        # Results of one shape leave the branch as one array: each output of a conditional is a kernel of
        # its own, and a joint's angular stage (5 results) cost 5 kernels per joint and sweep at batch 1.
        packed = jax.lax.cond(token >= 0, lambda *a: jnp.stack(jax.tree.leaves(fn(*a))),
                              lambda *a: jnp.zeros((len(leaves),) + leaves[0].shape, leaves[0].dtype), *args)
        return jax.tree.unflatten(tree, list(packed))

    def zeros(*a):
        return jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)

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


def take_rows(x, idx, axis: int = 0, fill=None):
    """x's entries idx along `axis`. idx (n,): the same entries in every scene (plain indexing). idx (n, B):
    each scene its own, for a batch-last x (..., B) (the broad phase's per-scene candidates; step.py).

    Per scene, the axis and the batch are flattened into one axis of N * B and gathered at idx * B + scene,
    so no scene's index reaches another scene's data. fill: the value at out-of-range indices (None: every
    index is in range).
    """
    if jnp.ndim(idx) == 1:  # as given: a numpy index stays a compile-time constant, as in plain indexing
        if fill is None:
            return x[(slice(None),) * (axis % x.ndim) + (idx,)]
        return jnp.take(x, idx, axis=axis, mode="fill", fill_value=fill)
    axis = axis % x.ndim
    if axis != x.ndim - 2:  # bring the axis next to the batch, where the flat gather needs no transpose
        return jnp.moveaxis(take_rows(jnp.moveaxis(x, axis, -2), idx, -2, fill), -2, axis)
    N, B = x.shape[-2:]
    flat = scene_rows(jnp.minimum(jnp.asarray(idx), N), B)
    if fill is None:
        return gather_scene_rows(x, flat)
    out = jnp.take(x.reshape(x.shape[:-2] + (N * B,)), flat.reshape(-1), axis=-1, mode="fill", fill_value=fill)
    return out.reshape(x.shape[:-2] + flat.shape)


def pad_rows(x, m: int):
    """Append zero rows (axis 0) so there are m: the static dummy body that makes the body count even."""
    return jnp.pad(x, [(0, m - x.shape[0])] + [(0, 0)] * (x.ndim - 1))


def scene_rows(idx, B: int):
    """(..., B) per-scene row indices idx -> indices into the flattened (N * B) axis of a batch-last array."""
    return idx * B + jnp.arange(B, dtype=idx.dtype)


def gather_scene_rows(x, flat):
    """x (..., N, B) at flat indices (..., B) from scene_rows, every index in range -> (...,) + flat.shape."""
    out = x.reshape(x.shape[:-2] + (-1,)).at[..., flat.reshape(-1)].get(mode="promise_in_bounds")
    return out.reshape(x.shape[:-2] + flat.shape)
