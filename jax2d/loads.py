"""Resting loads: the weight each contact carries at rest, passed down the contact graph (contact_solver.prepare).

A body resting on others hands its weight, and the weight resting on it, to the contacts below it (those
whose normal has a part against gravity), shared in proportion to that part. `LOAD_ROUNDS` rounds pass it down
that many bodies: a box on a box on a box on the floor. The estimate is made from the masses, the gravity and
which pairs touch at the step's start, so it does not follow the contacts' own impulses: a stiffness set from
last step's impulses (which swing while a stack settles) pumped energy into a bouncing 100:1 stack (its
second bounce went deeper than its first), and one from this estimate does not.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jax2d.math2d import ordered_sum, safe_inverse, scene_rows, take_rows

LOAD_ROUNDS = 3  # bodies a weight is passed down (a 3-box stack's top box reaches the floor's contact)


def per_body(on_a, on_b, a, b, num_rows: int):
    """(num_rows, *batch): each body's sum of on_a over the slots where it is side a and of on_b where it is
    side b; on_a, on_b (S, *batch). a, b: (S,) the same pairs in every scene, or (S, B) each scene its own
    (broad_phase's per-scene candidates, batch-last).

    With the same pairs in every scene, each body's slots are known when the step is traced: the sum is a
    gather of its slots' rows and an ordered sum over them (math2d.ordered_sum: the same bits at every batch
    width). A scatter-add (jax.ops.segment_sum) cost 5-10 % of a step at batch 256 on the CPU."""
    if jnp.ndim(a) == 1:
        a, b = np.asarray(a), np.asarray(b)
        rows = [np.concatenate([np.flatnonzero(a == m), len(a) + np.flatnonzero(b == m)]) for m in range(num_rows)]
        width = max(len(r) for r in rows)
        if width == 0:
            return jnp.zeros((num_rows,) + on_a.shape[1:], on_a.dtype)
        # every body's slot rows, padded with a row of zeros (index 2S)
        index = np.stack([np.pad(r, (0, width - len(r)), constant_values=2 * len(a)) for r in rows])
        both = jnp.concatenate([on_a, on_b, jnp.zeros_like(on_a[:1])])
        return ordered_sum(both[index], axis=1)
    B = on_a.shape[-1]
    total = jnp.zeros((num_rows * B,), on_a.dtype)
    for values, idx in ((on_a, a), (on_b, b)):
        total = total.at[scene_rows(idx, B).reshape(-1)].add(values.reshape(-1))
    return total.reshape((num_rows, B))


def resting_loads(a, b, nx, ny, inv_mass, gravity, touching):
    """(S, *batch) the force along each slot's normal that carries, at rest, the weight on its upper body.

    a, b: the slots' bodies ((S,) or (S, B)); nx, ny: the normal from a to b (S, *batch); inv_mass: (M, *batch),
    0 for static bodies; gravity: (2, *batch); touching: (S, *batch) slots with a point."""
    M = inv_mass.shape[0]
    g = jnp.sqrt(gravity[0] ** 2 + gravity[1] ** 2)
    along = gravity[0] * nx + gravity[1] * ny  # < 0: b rests on a; > 0: a rests on b
    upright = jnp.where(touching, jnp.abs(along) * safe_inverse(g), 0.0)  # the normal's part against gravity
    b_on_a = along < 0.0
    on_a = jnp.where(b_on_a, 0.0, upright)  # slots where a is the upper body, and their share of its weight
    on_b = jnp.where(b_on_a, upright, 0.0)
    supports = per_body(on_a, on_b, a, b, M)  # per upper body: the sum of its supports' parts
    share_a = on_a * safe_inverse(take_rows(supports, a))
    share_b = on_b * safe_inverse(take_rows(supports, b))
    dynamic = (inv_mass > 0.0).astype(jnp.float32)
    weight = safe_inverse(inv_mass) * g
    carried = weight
    for _ in range(LOAD_ROUNDS):
        down_a = share_b * take_rows(carried, b) * take_rows(dynamic, a)  # b's load handed to a moving a
        down_b = share_a * take_rows(carried, a) * take_rows(dynamic, b)
        carried = weight + per_body(down_a, down_b, a, b, M)
    return upright * (share_b * take_rows(carried, b) + share_a * take_rows(carried, a))
