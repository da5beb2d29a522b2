"""Level geometry in jnp, for the random level generator and the mutators: mass properties as jax2d computes them,
placement hulls (circles as circumscribed octagons), separation between hulls, how far a hull pokes out of the
walls, and which bodies joints link together. Fixed shapes, no Python control flow on traced values (jit, vmap).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from kinetix.level import (
    NUM_WALLS,
    Level,
)

# The world inside the standard walls (see kinetix.level.WALLS).
WORLD_LEFT, WORLD_RIGHT, WORLD_BOTTOM, WORLD_TOP = 0.0, 5.0, 0.4, 5.0
HULL = 8  # vertex slots of the placement hulls (circles are approximated by circumscribed octagons)
BIG = 1e9


# ---------------------------------------------------------------- geometry in jnp


def _cross(ax, ay, bx, by):
    return ax * by - ay * bx


def rotate(angle, v):
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def _next_index(n, size):
    i = jnp.arange(size)
    return jnp.where(i >= n - 1, 0, i + 1)


def polygon_mass_properties(vertices: jax.Array, n: jax.Array, density: jax.Array):
    """(mass, inertia about the centroid, centroid) of a padded convex polygon, in jnp (as jax2d.geometry).

    Triangles (origin, v_i, v_i+1) over the n real edges; their signed areas and second moments about
    the origin add up for any origin, and the parallel-axis step is tiny when the origin is the centroid.
    """
    v = vertices
    w = v[_next_index(n, v.shape[0])]
    real = jnp.arange(v.shape[0]) < n
    cr = jnp.where(real, _cross(v[:, 0], v[:, 1], w[:, 0], w[:, 1]), 0.0)
    area = 0.5 * jnp.sum(cr)
    safe_area = jnp.where(jnp.abs(area) > 0, area, 1.0)
    centroid = jnp.sum((cr / 6.0)[:, None] * (v + w), axis=0) / safe_area
    second = jnp.sum(cr / 12.0 * (jnp.sum(v * v, 1) + jnp.sum(v * w, 1) + jnp.sum(w * w, 1)))
    mass = density * area
    inertia = density * second - mass * jnp.sum(centroid * centroid)
    return mass, inertia, centroid


def circle_mass_properties(radius, density):
    mass = jnp.pi * radius * radius * density
    return mass, 0.5 * mass * radius * radius


def body_mass_properties(level: Level) -> tuple[jax.Array, jax.Array]:
    """(mass (N,), inertia (N,)) of every body slot from its shape and density, fixed or not."""
    b = level.sim.bodies
    P = level.sim.num_polygons
    pm, pi, _ = jax.vmap(polygon_mass_properties)(b.vertices, b.n_vertices, b.density[:P])
    cm, ci = circle_mass_properties(b.radius, b.density[P:])
    return jnp.concatenate([pm, cm]), jnp.concatenate([pi, ci])


def octagon(radius):
    """Circumscribed octagon of a circle: a conservative polygon for placement tests."""
    theta = jnp.arange(HULL) * (2 * jnp.pi / HULL)
    r = radius / jnp.cos(jnp.pi / HULL)
    return jnp.stack([r * jnp.cos(theta), r * jnp.sin(theta)], axis=-1)


def pad_hull(vertices, n):
    """(HULL, 2) vertices, padding repeating the last real vertex (so padded edges have zero length)."""
    V = vertices.shape[0]
    v = jnp.concatenate([vertices, jnp.repeat(vertices[-1:], HULL - V, axis=0)]) if V < HULL else vertices
    return jnp.where((jnp.arange(HULL) < n)[:, None], v, v[n - 1])


def body_hulls(level: Level) -> tuple[jax.Array, jax.Array]:
    """(hull (N, HULL, 2) body-frame vertices, n (N,)) of every body slot: polygons as they are, circles as octagons."""
    b = level.sim.bodies
    poly = jax.vmap(pad_hull)(b.vertices, b.n_vertices)
    circ = jax.vmap(octagon)(b.radius)
    hull = jnp.concatenate([poly, circ])
    n = jnp.concatenate([b.n_vertices, jnp.full(b.radius.shape, HULL, jnp.int32)])
    return hull, n


def world_hulls(position, angle, hull):
    """World-frame hull vertices: (..., 2) positions, (...,) angles, (..., HULL, 2) hulls."""
    return position[..., None, :] + rotate(angle[..., None], hull)


def _face_separation(w1, n1, w2, n2):
    """Largest over the real edges of w1 of the smallest signed distance of w2's real vertices to that edge."""
    i = jnp.arange(HULL)
    nxt = jnp.roll(w1, -1, axis=0)
    nxt = jnp.where((i == n1 - 1)[:, None], w1[0], nxt)
    e = nxt - w1
    length = jnp.sqrt(jnp.sum(e * e, axis=1))
    ok = (i < n1) & (length > 1e-9)
    safe = jnp.where(ok, length, 1.0)
    nx, ny = e[:, 1] / safe, -e[:, 0] / safe
    d = nx[:, None] * (w2[None, :, 0] - w1[:, None, 0]) + ny[:, None] * (w2[None, :, 1] - w1[:, None, 1])
    d = jnp.where((i < n2)[None, :], d, BIG)
    return jnp.max(jnp.where(ok, jnp.min(d, axis=1), -BIG))


def separation(w1, n1, w2, n2):
    """Separating-axis estimate between two convex world hulls: the gap if apart, minus the overlap depth if not."""
    return jnp.maximum(_face_separation(w1, n1, w2, n2), _face_separation(w2, n2, w1, n1))


def wall_excess(world, n):
    """How far the hull reaches past the nearest wall (negative: its distance inside the world)."""
    real = jnp.arange(HULL) < n
    x, y = world[..., 0], world[..., 1]
    out = jnp.maximum(jnp.maximum(WORLD_LEFT - x, x - WORLD_RIGHT), jnp.maximum(WORLD_BOTTOM - y, y - WORLD_TOP))
    return jnp.max(jnp.where(real, out, -BIG))


def joint_groups(level: Level) -> jax.Array:
    """(N,) int32: for every body, the smallest index of the bodies linked to it by chains of active joints.

    Bodies of one group never collide with each other (the engine filters jointed pairs).
    """
    j = level.sim.joints
    return groups_from_joints(j.a, j.b, j.active, level.sim.num_bodies)


def groups_from_joints(a, b, active, num_bodies: int) -> jax.Array:
    """joint_groups from the joint arrays (J,): each body's label is the smallest index in its group.

    Union by relabelling, one joint after the other: a joint whose bodies carry labels lo < hi gives every body
    labelled hi the label lo, so after the last joint each chain carries its smallest index. J elementwise
    rounds over the N labels, without matrix products or scatters: in the entity observation (attention mask
    1) at batch 256 that ran env rollouts s +11 % and l +1 % against a transitive closure by repeated squaring
    (docs/engine.md, "The observation's masks")."""
    labels = jnp.arange(num_bodies, dtype=jnp.int32)
    for k in range(a.shape[0]):
        la, lb = labels[a[k]], labels[b[k]]
        merge = active[k] & (labels == jnp.maximum(la, lb))
        labels = jnp.where(merge, jnp.minimum(la, lb), labels)
    return labels


def wall_mask(level: Level) -> np.ndarray:
    """(N,) constant bool: the standard wall slots."""
    return np.arange(level.sim.num_bodies) < NUM_WALLS


def set_fixed(level: Level, fixed: jax.Array) -> Level:
    """Bodies where `fixed` (N,) is True become static, the others get inverse mass and inertia from their shape."""
    b = level.sim.bodies
    mass, inertia = body_mass_properties(level)
    dynamic = b.active & ~fixed
    safe = lambda x: jnp.where(dynamic, x, 1.0)
    bodies = dataclasses.replace(
        b,
        inv_mass=jnp.where(dynamic, 1.0 / safe(mass), 0.0),
        inv_inertia=jnp.where(dynamic, 1.0 / safe(inertia), 0.0),
        velocity=jnp.where(dynamic[:, None], b.velocity, 0.0),
        angular_velocity=jnp.where(dynamic, b.angular_velocity, 0.0),
    )
    return dataclasses.replace(level, sim=dataclasses.replace(level.sim, bodies=bodies))
