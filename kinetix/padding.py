"""A level in a larger size class, under `jit` and `vmap`: `pad_level(level, "l")`.

Random levels of several size classes train one agent in one compiled program (`random-all` in
kinetix.level_source): each is generated in its own class and padded to the largest. Bodies keep their order
(polygons, then circles); the new slots are the target class's empty slots, so they are inactive and the
physics of the active entities is that of the original level. Joint and thruster body indices are remapped
(circles move up by the added polygon slots).

The contact warm-start history is not carried over (its rows follow the target's pair layout): a padded
level starts with none, as every freshly reset level does. kinetix.levels.resize is the host-side, general
counterpart (it rebuilds the level from its description and may also shrink it).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from kinetix.level import Level, SizeClass, empty_level, size_class, size_of

_BODY_ROWS = ("position", "angle", "velocity", "angular_velocity", "inv_mass", "inv_inertia", "density", "friction",
              "restitution", "collision_mode", "active")


@functools.cache
def constant_empty_level(size: SizeClass) -> Level:
    """empty_level(size) as concrete constants, even when first called inside a trace (cached per size class)."""
    with jax.ensure_compile_time_eval():
        return empty_level(size)


def _fits(small, large) -> bool:
    return (small.polygons <= large.polygons and small.circles <= large.circles and small.joints <= large.joints
            and small.thrusters <= large.thrusters and small.max_vertices == large.max_vertices)


def pad_level(level: Level, size: SizeClass | str) -> Level:
    """`level` in the (at least as large) size class `size`: same entities, extra slots inactive. Pure JAX."""
    size = size_class(size)
    src, dst = level.capacity, size.capacity
    if not _fits(src, dst):
        raise ValueError(f"a level of size {size_of(level).name} ({src}) does not fit in size {size.name} ({dst}); "
                         f"padding only grows a level (same max_vertices)")
    if src == dst:
        return level
    base = constant_empty_level(size)
    P, Pn = src.polygons, dst.polygons

    def bodies_rows(old, new):  # polygons first, then circles
        return jnp.concatenate([old[:P], new[P:Pn], old[P:], new[Pn + src.circles:]])

    def rows(old, new):  # joints, thrusters and per-polygon / per-circle arrays: the old rows first
        return jnp.concatenate([old, new[old.shape[0]:]])

    def body_index(i):
        return jnp.where(i < P, i, i - P + Pn).astype(i.dtype)

    ob, nb = level.sim.bodies, base.sim.bodies
    bodies = dataclasses.replace(
        nb, **{f: bodies_rows(getattr(ob, f), getattr(nb, f)) for f in _BODY_ROWS},
        vertices=rows(ob.vertices, nb.vertices), n_vertices=rows(ob.n_vertices, nb.n_vertices),
        radius=rows(ob.radius, nb.radius))
    joints = jax.tree.map(rows, level.sim.joints, base.sim.joints)
    joints = dataclasses.replace(joints, a=rows(body_index(level.sim.joints.a), base.sim.joints.a),
                                 b=rows(body_index(level.sim.joints.b), base.sim.joints.b))
    thrusters = jax.tree.map(rows, level.sim.thrusters, base.sim.thrusters)
    thrusters = dataclasses.replace(thrusters, body=rows(body_index(level.sim.thrusters.body), base.sim.thrusters.body))
    sim = dataclasses.replace(base.sim, bodies=bodies, joints=joints, thrusters=thrusters, gravity=level.sim.gravity,
                              frozen=level.sim.frozen)
    return Level(sim=sim, roles=bodies_rows(level.roles, base.roles),
                 motor_bindings=rows(level.motor_bindings, base.motor_bindings),
                 motor_auto=rows(level.motor_auto, base.motor_auto),
                 thruster_bindings=rows(level.thruster_bindings, base.thruster_bindings))
