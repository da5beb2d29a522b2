"""The point and weld rows of every joint in a scene as one linear system, solved directly.

Joints are solved one after another (Gauss-Seidel) in the substeps, and a few sweeps do not
converge where a light body carries several joints with anchors far from its centre: each
joint's solve moves the light body alone and undoes the previous one (docs/engine.md: a
0.02 kg hub whose effective mass at its anchors was 30-400x smaller than at the other ends
tore apart and reached the speed clamp). The joint projection (joint_solver.project) solves
all rows at once, A lambda = -(Cdot + bias) with A = J M^-1 J^T, which is exact whatever the
mass ratios.

Rows: three per joint slot, (x, y, angle) in that order. A revolute joint uses x and y, a
weld all three. Unused rows (a revolute joint's angle, inactive slots) are identity rows with
a zero right-hand side, so the system has the same size, 3J, for every level of a capacity.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jax2d.math2d import ordered_sum

# Added to the diagonal, relative to it, before the elimination. A is only positive
# semi-definite: rows that repeat others (a loop of welds, two welds on one pair of bodies) make
# it singular. The multipliers such rows get along the null space of J^T move no body; this
# keeps them finite. It also bounds the condition number a light hub gives A.
REGULARISATION = 1e-5


def row_mask(active, weld):
    """(3J, *batch) 1 for the rows a joint uses: x and y of every active joint, the angle of welds."""
    return jnp.stack([active, active, weld], axis=1).reshape((-1,) + active.shape[1:])


def matrix(ends, mask):
    """A = J M^-1 J^T over the rows `mask` marks, identity on the others: (3J, 3J, *batch).

    ends: per joint end (a then b), a tuple (body index, inverse mass, inverse inertia,
    anchor offset x, anchor offset y), each (J, *batch). Row j's Jacobian on the body at an end
    with anchor offset r is s [[1, 0, -ry], [0, 1, rx], [0, 0, 1]] (s = -1 at a, +1 at b), so a
    shared body with inverse mass m and inertia i adds s s' (m P + i u u'^T), with P = diag(1, 1, 0)
    and u = (-ry, rx, 1). Rows couple only through shared moving bodies; a static body has zero
    inverse mass and inertia. Built by broadcasting in (J, 3, J, 3, *batch) layout, without sums
    over bodies or transposes.
    """
    batch = ends[0][0].shape[1:]
    trail = (None,) * len(batch)
    plane = jnp.asarray([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]], jnp.float32)
    plane = plane[(None, slice(None), None, slice(None)) + trail]

    def lever(sign, rx, ry):
        return sign * jnp.stack([-ry, rx, jnp.ones_like(rx)], axis=1)  # (J, 3, *batch)

    a = 0.0
    for sign_e, (body_e, m_e, i_e, rx_e, ry_e) in zip((-1.0, 1.0), ends, strict=True):
        u_e = lever(sign_e, rx_e, ry_e)
        for sign_f, (body_f, _, _, rx_f, ry_f) in zip((-1.0, 1.0), ends, strict=True):
            u_f = lever(sign_f, rx_f, ry_f)
            shared = (body_e[:, None] == body_f[None, :]).astype(jnp.float32)[:, None, :, None]  # (J, 1, J, 1, *b)
            a = a + shared * ((sign_e * sign_f) * m_e[:, None, None, None] * plane
                              + i_e[:, None, None, None] * u_e[:, :, None, None] * u_f[None, None])
    n = 3 * ends[0][0].shape[0]
    a = a.reshape((n, n) + batch)
    eye = jnp.eye(n, dtype=jnp.float32).reshape((n, n) + (1,) * len(batch))
    return a * mask[:, None] * mask[None, :] + eye * (1.0 - mask[:, None])


def solve(a, rhs: tuple[jax.Array, ...], order, count) -> tuple[jax.Array, ...]:
    """x with (A + regularisation) x = r for each right-hand side r in `rhs`, for a (n, n, *batch) and
    each r (n, *batch). The inverse is computed once and serves them all.

    A^-1 by Gauss-Jordan elimination in its symmetric form (the sweep operator: sweeping pivot
    k leaves -(A restricted to the swept rows)^-1 in the swept block, in any order), then one
    matrix-vector product. Only the rows of joint slots live in some scene of the batch are
    swept (order: slots, live ones first; count: how many are live), in a loop, so the program
    is small whatever the capacity; the other rows get 0. A zero diagonal (a joint between two
    static bodies) gets 1, and then a multiplier that moves nothing. (LAPACK's Cholesky through
    jax.lax.linalg measured the same speed, but hung a batch split over two CPU devices.)
    """
    n = a.shape[0]
    rows = jnp.arange(n).reshape((n,) + (1,) * (a.ndim - 2))
    diagonal = jnp.moveaxis(jnp.diagonal(a, axis1=0, axis2=1), -1, 0)  # (n, *batch)
    eye = (rows[:, None] == rows[None, :]).astype(a.dtype)  # (n, n, 1...)
    a = a + eye * (REGULARISATION * diagonal + (diagonal <= 0.0))[None, :]

    def sweep(k, a):
        row = jax.lax.dynamic_index_in_dim(a, k, axis=0, keepdims=False)  # (n, *batch), also column k
        inv = 1.0 / jax.lax.dynamic_index_in_dim(row, k, axis=0, keepdims=False)
        scaled = row * inv
        at_k = rows == k  # (n, 1...)
        on_row, on_column = at_k[:, None], at_k[None, :]
        # Row and column k are set, not updated: a_kj - a_kk (a_kj / a_kk) would leave a rounding
        # residue the size of a_kj's last bit, large against the swept values.
        edge = jnp.where(on_row & on_column, -inv, jnp.where(on_row, scaled[None, :], scaled[:, None]))
        return jnp.where(on_row | on_column, edge, a - row[:, None] * scaled[None, :])

    def joint(i, carry):  # a joint slot's three rows per loop iteration: fewer iterations, fewer waits
        a, swept_rows = carry
        first = 3 * order[i]
        for r in range(3):
            a = sweep(first + r, a)
        return a, swept_rows | ((rows >= first) & (rows < first + 3))

    a, swept_rows = jax.lax.fori_loop(0, count, joint, (a, jnp.zeros(rows.shape, bool)))
    kept = swept_rows.astype(a.dtype)
    inverse = a * (kept[:, None] * kept[None, :])
    # in index order (math2d.ordered_sum), so a scene's multipliers do not depend on the batch it is in
    return tuple(-ordered_sum(inverse * r[None], axis=1) for r in rhs)
