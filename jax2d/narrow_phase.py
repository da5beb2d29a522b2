"""The narrow phase over every pair slot, the step's reach that sets its margin, and the pair filter.

    step_reach      how far any point of each body can move in one step
    narrow_phase    contact manifolds for every slot of the all-pairs layout (pairs.py), batch-last
    pair_filter     which slots' bodies may collide (active, not both static, modes agree, not jointed)
    joint_connected bodies linked through any chain of joints (the filter's "jointed")

The broad phase (broad_phase.py) runs the same collide calls on each scene's candidate pairs, through
`over_pairs_and_batch`.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jax2d.collide import Manifold, collide_circles, collide_polygon_circle_rotated, collide_polygons_rotated
from jax2d.math2d import pad_rows, rotation, stored, take_rows
from jax2d.pairs import CIRCLE_CIRCLE, CIRCLE_POLY, PADDING, POLY_CIRCLE, POLY_POLY, ContactLayout
from jax2d.state import Bodies, Joints, SimState, modes_agree


def step_reach(state: SimState, dt) -> jax.Array:
    """(N, *batch) how far any point of each body can move in one step, batch-last: its speed, its spin times
    its farthest point, and gravity's gain, over dt. See narrow_phase: the speculative margin of a pair is the
    sum of its bodies' reaches on top of SimParams.speculative_distance."""
    b = state.bodies
    extent = jnp.concatenate([jnp.max(jnp.linalg.norm(b.vertices, axis=-2), axis=1), b.radius])
    speed = jnp.linalg.norm(b.velocity, axis=1)
    gain = jnp.linalg.norm(state.gravity, axis=0) * dt
    return dt * (speed + jnp.abs(b.angular_velocity) * extent + gain)


def narrow_phase(layout: ContactLayout, b: Bodies, speculative, reach=None, token=None) -> Manifold:
    """Manifolds for every slot, batch-last: each kind of pair is evaluated on its own constant index list.

    b: bodies with the batch as the last axis of every leaf; speculative: (*batch); reach: None or (N, *batch)
    how far each body can move in this step (step_reach).

    A pair's points are kept while their separation is below the speculative distance plus both bodies'
    reach, so a contact exists before any body can cross the gap in one step, however fast it moves (up to
    the speed clamp): the solver removes only the approaching velocity beyond the gap (s / h), so a far
    point costs nothing but its solve. Without the reach, a 0.1 m ball at 30 m/s passed through a 0.1 m
    wall in 4 of 5 tries.
    Returns manifold fields with the batch last, e.g. normal (S, 2, B). The collide functions
    are written for one pair; they map over the batch as the minor axis (each of a polygon's
    V edges is then a row of B scenes) and over the pairs as the major one. With the pairs
    minor (a vmap of the per-scene narrow phase), XLA's loops ran over rows of V = 8 floats
    and the stage took twice as long at s, batch 2048.
    """
    P = b.vertices.shape[0]
    pos, ang, verts, nv, rad = b.position, b.angle, b.vertices, b.n_vertices, b.radius
    batch, mapped, spec, reach = pair_inputs(b, speculative, reach)

    def margin(i, j):
        return spec + reach[i] + reach[j]

    kinds = layout.by_kind
    parts = []
    i, j = layout.slot_a[kinds[POLY_POLY]], layout.slot_b[kinds[POLY_POLY]]
    # Polygon-circle pairs in either order share one call; circle-first pairs flip the normal.
    pc, cp = kinds[POLY_CIRCLE], kinds[CIRCLE_POLY]
    poly = np.concatenate([layout.slot_a[pc], layout.slot_b[cp]])
    circle = np.concatenate([layout.slot_b[pc], layout.slot_a[cp]])

    def rotations(a, b, p):  # (pairs, 2, *batch) each, stored once (math2d.stored)
        return tuple(jnp.moveaxis(rotation(x), 0, 1) for x in (a, b - a, p))

    rot_a, rot_ba, rot_p = stored(token, rotations, ang[i], ang[j], ang[poly])
    if len(i):
        parts.append(mapped(collide_polygons_rotated, 8)(
            pos[i], rot_a, verts[i], nv[i], pos[j], rot_ba, verts[j], nv[j], margin(i, j)))
    if len(poly):
        m = mapped(collide_polygon_circle_rotated, 6)(
            pos[poly], rot_p, verts[poly], nv[poly], pos[circle], rad[circle - P], margin(poly, circle))
        sign = np.concatenate([np.ones(len(pc)), -np.ones(len(cp))]).astype(np.float32)
        parts.append(dataclasses.replace(m, normal=m.normal * sign.reshape((-1, 1) + (1,) * len(batch))))
    i, j = layout.slot_a[kinds[CIRCLE_CIRCLE]], layout.slot_b[kinds[CIRCLE_CIRCLE]]
    if len(i):
        parts.append(mapped(collide_circles, 4)(pos[i], rad[i - P], pos[j], rad[j - P], margin(i, j)))
    S = layout.num_slots
    if not parts:
        return empty_rows(S, batch)
    empty = empty_rows(1, batch)  # the row padding slots take
    rows = jax.tree.map(lambda *xs: jnp.concatenate(xs), *parts, empty)
    # Every slot picks its row with a constant index (padding slots take the empty row).
    return jax.tree.map(lambda x: x[layout.gather], rows)


def pair_inputs(b: Bodies, speculative, reach) -> tuple[tuple, object, jax.Array, jax.Array]:
    """What both narrow phases (this one and broad_phase.collide_candidates) start from, for batch-last bodies:
    the batch shape, the collide mapper over pairs and batch (over_pairs_and_batch), the speculative distance
    per scene and each body's reach (zero where reach is None)."""
    batch = b.position.shape[2:]
    mapped = functools.partial(over_pairs_and_batch, batch=batch)
    spec = jnp.broadcast_to(jnp.asarray(speculative, jnp.float32), batch)
    reach = jnp.zeros((b.active.shape[0],) + batch, jnp.float32) if reach is None else reach
    return batch, mapped, spec, reach


def empty_rows(n: int, batch: tuple) -> Manifold:
    """n manifold rows with no point and normal (0, 1), batch last: what padding slots and rows hold."""
    empty = Manifold(jnp.zeros((n, 2)).at[:, 1].set(1.0), jnp.zeros((n, 2, 2)), jnp.zeros((n, 2)),
                     jnp.full((n, 2), -1, jnp.int32), jnp.zeros((n, 2), bool))
    return jax.tree.map(lambda x: jnp.broadcast_to(x.reshape(x.shape + (1,) * len(batch)), x.shape + batch), empty)


def over_pairs_and_batch(collide, n: int, batch: tuple):
    """A collide function of n pair arguments plus the pair's speculative margin, mapped over the batch
    axes (minor, innermost last) and the pairs (major)."""
    inner = collide
    for _ in batch:
        inner = jax.vmap(inner, in_axes=(-1,) * (n + 1), out_axes=-1)
    return jax.vmap(inner, in_axes=(0,) * (n + 1))


def pair_filter(layout: ContactLayout, b: Bodies, jointed, M: int) -> jax.Array:
    """(S, *batch) whether each slot's bodies may collide: active, not both static, modes agree, not jointed."""
    a, c = layout.slot_a, layout.slot_b  # (S,), or (S, B): each scene's own pairs (broad_phase)
    ta, tc = functools.partial(take_rows, idx=a), functools.partial(take_rows, idx=c)
    active = pad_rows(b.active, M)
    moving = pad_rows(b.active & (b.inv_mass > 0), M)
    mode = pad_rows(b.collision_mode, M)
    real = layout.slot_kind != PADDING
    if real.ndim == 1:
        real = real.reshape((-1,) + (1,) * (active.ndim - 1))
    return real & ta(active) & tc(active) & (ta(moving) | tc(moving)) & modes_agree(ta(mode), tc(mode)) & ~jointed


UNROLLED_ROUNDS = 8  # joint_labels writes out this many rounds or fewer; more run in a loop (xl: 24)


def joint_labels(joints: Joints, M: int) -> jax.Array:
    """(M,) int for one scene: each body's joint group, the smallest body index it is linked to through any
    chain of joints (itself when it has no joint).

    Min-label propagation over the joint list: in every round each active joint gives both its bodies the
    smaller of their labels. A round carries the group's smallest label one joint further along every chain,
    and no chain is longer than the J joints, so J rounds reach the fixed point. Against the transitive
    closure by repeated squaring of the (M, M) link matrix that this replaced (log2 M matrix products):
    measured on the 2-core CPU, vmapped over a batch of 256 scenes, s (M 7, J 1) 371 -> 38 us,
    l (16, 6) 359 -> 71 us, xl (80, 24) 30 -> 0.9 ms; the same booleans. Inside a whole step that is within
    the noise at s, m and l and 1.5 % at xl batch 16 (docs/engine.md, Known problems)."""
    a = joints.a
    b = jnp.where(joints.active, joints.b, joints.a)  # an inactive joint links its body a to itself: no change

    def relax(_, labels):
        smaller = jnp.minimum(labels[a], labels[b])
        return labels.at[a].min(smaller).at[b].min(smaller)

    labels = jnp.arange(M, dtype=a.dtype)
    if a.shape[0] <= UNROLLED_ROUNDS:  # s, m, l: a loop would add its trip test to every step
        for _ in range(a.shape[0]):
            labels = relax(None, labels)
        return labels
    return jax.lax.fori_loop(0, a.shape[0], relax, labels)


def joint_connected(joints: Joints, M: int) -> jax.Array:
    """(M, M) bool for one scene: bodies linked through any chain of joints (each body to itself too)."""
    labels = joint_labels(joints, M)
    return labels[:, None] == labels[None, :]


def joint_labels_batch_last(joints: Joints, M: int) -> jax.Array:
    """(M, *batch) joint_labels for batch-last joints (every leaf's last axes are the batch)."""
    per_scene = functools.partial(joint_labels, M=M)
    for _ in range(joints.a.ndim - 1):
        per_scene = jax.vmap(per_scene, in_axes=-1, out_axes=-1)
    return per_scene(joints)
