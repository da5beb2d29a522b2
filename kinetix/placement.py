"""Building bodies into a level at random, the shape builders the generator (kinetix.generate) and the mutators
(kinetix.mutate) share: the generator's knobs (GeneratorParams), streams of random numbers read in a fixed order,
random shapes and joints, placement proposals scored by overlap, and add_body / add_thruster / set_fixed.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jax2d.state import COLLIDE_NORMAL
from kinetix.geometry import (
    BIG,
    HULL,
    WORLD_BOTTOM,
    WORLD_LEFT,
    WORLD_RIGHT,
    WORLD_TOP,
    body_hulls,
    body_mass_properties,
    circle_mass_properties,
    joint_groups,
    octagon,
    pad_hull,
    polygon_mass_properties,
    rotate,
    separation,
    wall_excess,
    wall_mask,
    world_hulls,
)
from kinetix.level import (
    NUM_THRUSTER_BINDINGS,
    NUM_WALLS,
    ROLE_NONE,
    Level,
)


@dataclasses.dataclass(frozen=True)
class GeneratorParams:
    """Knobs of the random level generator and mutators. Plain numbers, hashable (a static jit argument).

    Lengths in m, densities in kg/m^2, angles in rad; "chance" values are probabilities.
    """

    # Shapes. Polygon sizes are circumradii before the aspect stretch; circles use their radius.
    min_polygon_size: float = 0.12
    max_polygon_size: float = 0.5
    min_circle_radius: float = 0.08
    max_circle_radius: float = 0.35
    large_shape_chance: float = 0.15  # chance that a shape is scaled up by large_shape_factor
    large_shape_factor: float = 1.6
    max_aspect: float = 3.0  # polygons are stretched by up to this ratio along their own axes
    rectangle_chance: float = 0.5
    triangle_chance: float = 0.2  # the rest: irregular convex polygons with 4..max_vertices vertices
    vertex_jitter: float = 0.3  # irregular polygons: angular jitter of each vertex, in units of the even spacing
    axis_aligned_chance: float = 0.5  # free shapes start at angle 0 or pi/2 (else a uniform angle)
    min_density: float = 0.5
    max_density: float = 1.5
    min_friction: float = 0.3
    max_friction: float = 1.0
    bouncy_chance: float = 0.1  # restitution uniform in [0.2, max_restitution] (else 0)
    max_restitution: float = 0.6

    # Structure: what each body slot after the goal roots and the forced motor holds.
    connected_chance: float = 0.4  # a shape jointed to an earlier one
    free_chance: float = 0.35  # a free shape (the rest: the slot stays empty)
    fixed_chance: float = 0.2  # roots and free shapes are fixed (static) with this chance; jointed ones never
    red_chance: float = 0.15  # non-goal shapes are red hazards with this chance
    floor_red_chance: float = 0.1
    # Control mode weights: a motor joint, a thruster, or both.
    control_motor_weight: float = 1.0
    control_thruster_weight: float = 1.0
    control_both_weight: float = 1.0

    # Joints.
    revolute_chance: float = 0.75  # else a fixed (weld) joint
    motor_on_chance: float = 0.8
    min_motor_speed: float = 0.5  # units of LevelParams.base_motor_speed
    max_motor_speed: float = 3.0
    min_motor_power: float = 0.5  # units of LevelParams.base_motor_power
    max_motor_power: float = 2.0
    wheel_chance: float = 0.6  # a jointed circle is pinned at its centre (a wheel) with this chance
    wheel_max_power: float = 1.0  # strong wheel motors make assemblies jump about
    limit_chance: float = 0.3  # revolute joints that are not wheels get angle limits
    max_limit: float = math.pi  # limits are lower in [-max_limit, -0.1], upper in [0.1, max_limit]

    # Thrusters.
    extra_thruster_chance: float = 0.3  # each thruster slot beyond the forced one
    min_thrust_to_weight: float = 1.0  # force at full action / weight of the assembly it is on
    max_thrust_to_weight: float = 3.0
    thruster_align_chance: float = 0.8  # the force points through the centre of mass (else any direction)
    max_thruster_power: float = 5.0  # units of base_thruster_power
    base_thruster_power: float = 10.0  # N per unit of power; must match LevelParams.base_thruster_power

    # Placement.
    proposals: int = 8  # candidate poses per shape; the least overlapping one is kept
    clearance: float = 0.02  # preferred gap to other shapes and the walls
    overlap_tolerance: float = 0.01  # largest overlap (m) a kept shape may have with a shape it collides with
    goal_spread: float = 0.5  # weight of the second goal root's distance from the first (m of overlap per m)
    gravity: float = -9.81


DEFAULT_PARAMS = GeneratorParams()


# ---------------------------------------------------------------- random numbers


class Stream:
    """Uniform [0, 1) numbers handed out in order, with the usual distributions built on them.

    Each `jax.random` call compiles its own hash (about 0.2 s of compile time each), so every operation
    draws all its numbers in one call up front and reads them from a Stream; indices are static.
    """

    def __init__(self, u: jax.Array):
        self.u = u
        self.used = 0

    @classmethod
    def of(cls, key: jax.Array, count: int) -> Stream:
        return cls(jax.random.uniform(key, (count,), jnp.float32))

    def take(self, shape=()) -> jax.Array:
        size = math.prod(shape)
        if self.used + size > self.u.shape[-1]:
            raise ValueError(f"random stream of {self.u.shape[-1]} numbers exhausted; draw more up front")
        out = self.u[..., self.used:self.used + size].reshape(self.u.shape[:-1] + tuple(shape))
        self.used += size
        return out

    def uniform(self, low, high, shape=()) -> jax.Array:
        return low + self.take(shape) * (high - low)

    def chance(self, p, shape=()) -> jax.Array:
        return self.take(shape) < p

    def angle(self) -> jax.Array:
        return self.uniform(-jnp.pi, jnp.pi)

    def randint(self, low, high) -> jax.Array:
        """An integer in [low, high) (high may be traced)."""
        return jnp.clip(jnp.floor(low + self.take() * (high - low)), low, high - 1).astype(jnp.int32)

    def choice(self, weights: jax.Array) -> jax.Array:
        """An index drawn with probability proportional to non-negative `weights` (0 if they are all 0)."""
        w = jnp.maximum(weights.astype(jnp.float32), 0.0)
        cumulative = jnp.cumsum(w)
        return jnp.minimum(jnp.sum(cumulative <= self.take() * cumulative[-1]), w.shape[0] - 1).astype(jnp.int32)

    def sub(self, count: int, each: int) -> jax.Array:
        """(count, each) numbers, to give `count` vmapped callees a Stream each."""
        return self.take((count, each))


def first_free(active: jax.Array, allowed=None) -> tuple[jax.Array, jax.Array]:
    """(index of the first inactive slot, whether there is one); `allowed` masks slots out."""
    free = ~active if allowed is None else ~active & allowed
    return jnp.argmax(free).astype(jnp.int32), jnp.any(free)


def _set(array, index, value, condition):
    """array with row `index` set to `value` where `condition` holds (else unchanged)."""
    return array.at[index].set(jnp.where(condition, jnp.asarray(value, array.dtype), array[index]))


# ---------------------------------------------------------------- shapes


class Shape(NamedTuple):
    """A sampled shape in its body frame (centred on its centroid), before it is placed."""

    is_circle: jax.Array  # bool
    vertices: jax.Array  # (V, 2) polygon vertices, counter-clockwise, padded with the last one
    n: jax.Array  # int32 polygon vertex count
    radius: jax.Array  # circle radius
    density: jax.Array
    friction: jax.Array
    restitution: jax.Array

    @property
    def hull(self):
        return jnp.where(self.is_circle, octagon(self.radius), pad_hull(self.vertices, self.n))

    @property
    def hull_n(self):
        return jnp.where(self.is_circle, HULL, self.n)

    def mass_properties(self):
        pm, pi, _ = polygon_mass_properties(self.vertices, self.n, self.density)
        cm, ci = circle_mass_properties(self.radius, self.density)
        return jnp.where(self.is_circle, cm, pm), jnp.where(self.is_circle, ci, pi)


def sample_polygon(u: Stream, max_vertices: int, params: GeneratorParams):
    """(vertices (max_vertices, 2) centred on the centroid, counter-clockwise, n) of a random convex polygon.

    Points at increasing angles on a circle are in convex position; stretching the circle along x and y
    (an affine map with positive determinant) keeps them convex and counter-clockwise.
    """
    V = max_vertices
    kind = u.take()
    rect = (kind < params.rectangle_chance) & (V >= 4)
    tri = ~rect & ((kind < params.rectangle_chance + params.triangle_chance) | (V < 4))
    n = jnp.where(rect, 4, jnp.where(tri, 3, u.randint(4, max(V, 4) + 1))).astype(jnp.int32)

    size = u.uniform(params.min_polygon_size, params.max_polygon_size)
    size = size * jnp.where(u.chance(params.large_shape_chance), params.large_shape_factor, 1.0)
    log_aspect = u.uniform(-math.log(params.max_aspect), math.log(params.max_aspect))
    sx, sy = size * jnp.exp(0.5 * log_aspect), size * jnp.exp(-0.5 * log_aspect)

    i = jnp.arange(V, dtype=jnp.float32)
    irregular = 2 * jnp.pi * (i + u.uniform(0.0, params.vertex_jitter, (V,))) / n + u.uniform(0.0, 2 * jnp.pi)
    theta = jnp.where(rect, jnp.pi / 4 + i * (jnp.pi / 2), irregular)
    points = jnp.stack([sx * jnp.cos(theta), sy * jnp.sin(theta)], axis=-1)
    points = jnp.where((jnp.arange(V) < n)[:, None], points, points[n - 1])
    _, _, centroid = polygon_mass_properties(points, n, 1.0)
    return points - centroid, n


def sample_shape(u: Stream, is_circle, max_vertices: int, params: GeneratorParams) -> Shape:
    """A random polygon or circle (chosen by `is_circle`) with random material."""
    vertices, n = sample_polygon(u, max_vertices, params)
    radius = u.uniform(params.min_circle_radius, params.max_circle_radius)
    radius = radius * jnp.where(u.chance(params.large_shape_chance), params.large_shape_factor, 1.0)
    bouncy = u.chance(params.bouncy_chance)
    return Shape(
        is_circle=jnp.asarray(is_circle),
        vertices=vertices,
        n=n,
        radius=radius,
        density=u.uniform(params.min_density, params.max_density),
        friction=u.uniform(params.min_friction, params.max_friction),
        restitution=jnp.where(bouncy, u.uniform(0.2, params.max_restitution), 0.0),
    )


def local_point(u: Stream, is_circle, vertices, n, radius, low, high):
    """A body-frame point inside a shape: a fraction in [low, high] of the way to a vertex (or the rim)."""
    fraction = u.uniform(low, high)
    vertex = vertices[u.randint(0, jnp.maximum(n, 1))]
    angle = u.angle()
    rim = radius * jnp.stack([jnp.cos(angle), jnp.sin(angle)])
    return fraction * jnp.where(is_circle, rim, vertex)


def body_shape(level: Level, index):
    """(is_circle, vertices (V, 2), n, radius) of body slot `index` (traced)."""
    b = level.sim.bodies
    P, C = level.sim.num_polygons, level.sim.num_circles
    is_circle = index >= P
    p = jnp.clip(index, 0, P - 1)
    radius = b.radius[jnp.clip(index - P, 0, C - 1)] if C > 0 else jnp.float32(0.0)
    return is_circle, b.vertices[p], b.n_vertices[p], radius


# ---------------------------------------------------------------- placement


def placement_cost(world, n, others_world, others_n, collides, params: GeneratorParams):
    """(cost, fits) of a hull at its world pose among other bodies.

    collides: (N,) which other bodies it may touch (active, not walls, not in its joint group).
    Cost adds every shortfall from the clearance and the wall excess; it fits when no overlap exceeds
    the tolerance and it lies inside the walls.
    """
    sep = jax.vmap(separation, in_axes=(None, None, 0, 0))(world, n, others_world, others_n)
    sep = jnp.where(collides, sep, BIG)
    excess = wall_excess(world, n)
    cost = jnp.sum(jax.nn.relu(params.clearance - sep)) + 10.0 * jax.nn.relu(excess + params.clearance)
    fits = (jnp.min(sep) >= -params.overlap_tolerance) & (excess <= 0.0)
    return cost, fits


class Joint(NamedTuple):
    """A sampled joint of a new body b to an existing body a (a traced record)."""

    fixed: jax.Array
    motor_on: jax.Array
    motor_speed: jax.Array
    motor_power: jax.Array
    limit_on: jax.Array
    lower: jax.Array
    upper: jax.Array
    wheel: jax.Array  # a circle pinned at its centre


def sample_joint(u: Stream, child_is_circle, force_motor, params: GeneratorParams) -> Joint:
    revolute = u.chance(params.revolute_chance) | force_motor
    wheel = child_is_circle & u.chance(params.wheel_chance) & revolute
    motor_on = revolute & (u.chance(params.motor_on_chance) | force_motor)
    max_power = jnp.where(wheel, min(params.wheel_max_power, params.max_motor_power), params.max_motor_power)
    power = params.min_motor_power + u.take() * jnp.maximum(max_power - params.min_motor_power, 0.0)
    speed = u.uniform(params.min_motor_speed, params.max_motor_speed)
    limit_on = revolute & ~wheel & u.chance(params.limit_chance)
    lower, upper = -u.uniform(0.1, params.max_limit), u.uniform(0.1, params.max_limit)
    zero = jnp.float32(0.0)
    return Joint(
        fixed=~revolute,
        motor_on=motor_on,
        # A weld has no motor or limits: keep those fields empty (as the level loader stores them).
        motor_speed=jnp.where(revolute, speed, zero),
        motor_power=jnp.where(revolute, power, zero),
        limit_on=limit_on,
        lower=jnp.where(limit_on, lower, zero),
        upper=jnp.where(limit_on, upper, zero),
        wheel=wheel,
    )


def free_pose(u: Stream, hull, params: GeneratorParams):
    """A random pose keeping the hull's bounding circle inside the walls (if it fits at all)."""
    bound = jnp.max(jnp.linalg.norm(hull, axis=-1)) + params.clearance

    def coordinate(low, high):
        lo, hi = low + bound, high - bound
        return jnp.where(lo < hi, u.uniform(0.0, 1.0) * (hi - lo) + lo, 0.5 * (low + high))

    position = jnp.stack([coordinate(WORLD_LEFT, WORLD_RIGHT), coordinate(WORLD_BOTTOM, WORLD_TOP)])
    aligned = u.chance(params.axis_aligned_chance)
    quarter = u.randint(0, 2) * (jnp.pi / 2)
    return position, jnp.where(aligned, quarter, u.angle())


class AddResult(NamedTuple):
    level: Level
    added: jax.Array  # bool
    index: jax.Array  # global body index of the new body (meaningless when not added)
    jointed: jax.Array  # bool: it was jointed to an existing body


ADD_BODY_DRAWS = 40  # numbers add_body reads besides its proposals
PROPOSAL_DRAWS = 16  # numbers each placement proposal reads


def add_body(key_or_stream, level: Level, params: GeneratorParams, *, is_circle, connect, force_motor=False,
             always=False, far_from=-1, fixed=False, role=ROLE_NONE, enabled=True) -> AddResult:
    """Add a random shape in the first free slot of its kind, placed by the best of `params.proposals` poses.

    connect: joint it to a random existing non-wall body (needs a free joint slot, else it is free);
    force_motor: that joint is a revolute motor; always: keep it even if it overlaps (it still must lie
    inside the walls); far_from: a body index the shape prefers to lie far from (-1: none);
    fixed / role: of the new body (a jointed body is never fixed); enabled: False makes it a no-op.
    Traced arguments are fine. The first argument is a key or a Stream of `add_body_draws(params)` numbers.
    """
    u = key_or_stream if isinstance(key_or_stream, Stream) else Stream.of(key_or_stream, add_body_draws(params))
    sim = level.sim
    b = sim.bodies
    P, C, J = sim.num_polygons, sim.num_circles, sim.num_joints
    N = P + C
    index_range = jnp.arange(N)

    is_circle = jnp.asarray(is_circle) if C > 0 and P > NUM_WALLS else jnp.asarray(C > 0)
    polygon_slot, polygon_free = first_free(b.active, (index_range >= NUM_WALLS) & (index_range < P))
    circle_slot, circle_free = first_free(b.active, index_range >= P)
    slot = jnp.where(is_circle, circle_slot, polygon_slot)
    has_slot = jnp.where(is_circle, circle_free, polygon_free)

    proposal_numbers = u.sub(params.proposals, PROPOSAL_DRAWS)
    shape = sample_shape(u, is_circle, sim.max_vertices, params)
    joint = sample_joint(u, is_circle, jnp.asarray(force_motor), params)
    hull, hull_n = shape.hull, shape.hull_n
    hulls, hull_counts = body_hulls(level)
    worlds = world_hulls(b.position, b.angle, hulls)
    groups = joint_groups(level)
    candidates = b.active & ~wall_mask(level)
    joint_slot, joint_free = first_free(sim.joints.active) if J > 0 else (0, False)
    connect = jnp.asarray(connect) & joint_free & jnp.any(candidates)
    far = jnp.clip(far_from, 0, N - 1)

    def proposal(numbers):
        v = Stream(numbers)
        free_position, free_angle = free_pose(v, hull, params)
        parent = v.choice(candidates)
        p_circle, p_vertices, p_n, p_radius = body_shape(level, parent)
        anchor_a = local_point(v, p_circle, p_vertices, p_n, p_radius, 0.3, 0.9)
        anchor_b = local_point(v, shape.is_circle, shape.vertices, shape.n, shape.radius, 0.4, 0.85)
        anchor_b = jnp.where(joint.wheel, 0.0, anchor_b)
        world_anchor = b.position[parent] + rotate(b.angle[parent], anchor_a)
        # Turn the child so that it reaches away from the parent's centre (within +-60 degrees), so
        # assemblies spread out instead of piling up on their first shape.
        outward = world_anchor - b.position[parent]
        away = jnp.where(jnp.linalg.norm(outward) > 1e-3, jnp.arctan2(outward[1], outward[0]), v.angle())
        away = away + v.uniform(-jnp.pi / 3, jnp.pi / 3)
        child_angle = away - jnp.arctan2(-anchor_b[1], -anchor_b[0])
        position = jnp.where(connect, world_anchor - rotate(child_angle, anchor_b), free_position)
        angle = jnp.where(connect, child_angle, free_angle)
        world = world_hulls(position, angle, hull)
        collides = candidates & ~(connect & (groups == groups[parent]))
        cost, fits = placement_cost(world, hull_n, worlds, hull_counts, collides, params)
        # Prefer lying far from `far_from` (the first goal root, for the second).
        distance = jnp.linalg.norm(position - b.position[far])
        cost = cost - jnp.where(far_from >= 0, params.goal_spread * jnp.minimum(distance, 3.0), 0.0)
        inside = wall_excess(world, hull_n) <= 0.0
        return cost, fits, inside, position, angle, parent, anchor_a, anchor_b

    cost, fits, inside, *chosen = jax.vmap(proposal)(proposal_numbers)
    # The cheapest proposal that fits, else (for `always`) the cheapest inside the walls.
    best = jnp.argmin(cost + jnp.where(fits, 0.0, 1e3) + jnp.where(inside, 0.0, 1e6))
    ok = jnp.asarray(enabled) & has_slot & jnp.where(always, inside[best], fits[best])
    position, angle, parent, anchor_a, anchor_b = (x[best] for x in chosen)

    fixed = jnp.asarray(fixed) & ~connect
    mass, inertia = shape.mass_properties()
    bodies = dataclasses.replace(
        b,
        position=_set(b.position, slot, position, ok),
        angle=_set(b.angle, slot, angle, ok),
        velocity=_set(b.velocity, slot, jnp.zeros(2), ok),
        angular_velocity=_set(b.angular_velocity, slot, 0.0, ok),
        inv_mass=_set(b.inv_mass, slot, jnp.where(fixed, 0.0, 1.0 / mass), ok),
        inv_inertia=_set(b.inv_inertia, slot, jnp.where(fixed, 0.0, 1.0 / inertia), ok),
        density=_set(b.density, slot, shape.density, ok),
        friction=_set(b.friction, slot, shape.friction, ok),
        restitution=_set(b.restitution, slot, shape.restitution, ok),
        collision_mode=_set(b.collision_mode, slot, COLLIDE_NORMAL, ok),
        active=_set(b.active, slot, True, ok),
        vertices=_set(b.vertices, jnp.clip(slot, 0, P - 1), shape.vertices, ok & ~is_circle),
        n_vertices=_set(b.n_vertices, jnp.clip(slot, 0, P - 1), shape.n, ok & ~is_circle),
        radius=_set(b.radius, jnp.clip(slot - P, 0, C - 1), shape.radius, ok & is_circle) if C > 0 else b.radius,
    )
    joints = sim.joints
    if J > 0:
        write = ok & connect
        values = dict(a=parent, b=slot, anchor_a=anchor_a, anchor_b=anchor_b, ref_angle=angle - b.angle[parent],
                      active=True, fixed=joint.fixed, motor_on=joint.motor_on, motor_speed=joint.motor_speed,
                      motor_power=joint.motor_power, limit_on=joint.limit_on, lower=joint.lower, upper=joint.upper,
                      impulse=jnp.zeros(joints.impulse.shape[1:]))
        joints = dataclasses.replace(joints, **{name: _set(getattr(joints, name), joint_slot, value, write)
                                                for name, value in values.items()})
    roles = _set(level.roles, slot, role, ok)
    level = dataclasses.replace(level, sim=dataclasses.replace(sim, bodies=bodies, joints=joints), roles=roles)
    return AddResult(level, ok, slot, ok & connect)


def add_body_draws(params: GeneratorParams) -> int:
    """How many uniform numbers add_body reads."""
    return ADD_BODY_DRAWS + params.proposals * PROPOSAL_DRAWS


THRUSTER_DRAWS = 8


def add_thruster(key_or_stream, level: Level, params: GeneratorParams, prefer=-1, allowed=True
                 ) -> tuple[Level, jax.Array]:
    """Attach a random thruster to a random dynamic non-wall body (preferring the joint group of body `prefer`).

    Its force at full action is a few times the weight of the dynamic bodies of that group. Returns the level
    and whether a thruster was added (a free slot and a dynamic body are needed, and `allowed`).
    """
    sim = level.sim
    if sim.num_thrusters == 0:
        return level, jnp.asarray(False)
    u = key_or_stream if isinstance(key_or_stream, Stream) else Stream.of(key_or_stream, THRUSTER_DRAWS)
    b = sim.bodies
    N = sim.num_bodies
    slot, free = first_free(sim.thrusters.active)
    dynamic = b.active & (b.inv_mass > 0) & ~wall_mask(level)
    groups = joint_groups(level)
    preferred = (prefer >= 0) & (groups == groups[jnp.clip(prefer, 0, N - 1)])
    body = u.choice(dynamic * jnp.where(preferred, 3.0, 1.0))
    ok = jnp.asarray(allowed) & free & jnp.any(dynamic)

    is_circle, vertices, n, radius = body_shape(level, body)
    anchor = local_point(u, is_circle, vertices, n, radius, 0.5, 1.0)
    # Aligned: the force pushes from the anchor through the centre of mass (no torque).
    aligned = u.chance(params.thruster_align_chance) & (jnp.linalg.norm(anchor) > 1e-3)
    angle = jnp.where(aligned, jnp.arctan2(-anchor[1], -anchor[0]), u.angle())
    mass, _ = body_mass_properties(level)
    group_mass = jnp.sum(jnp.where(dynamic & (groups == groups[body]), mass, 0.0))
    weight = group_mass * jnp.linalg.norm(sim.gravity)
    ratio = u.uniform(params.min_thrust_to_weight, params.max_thrust_to_weight)
    power = jnp.clip(ratio * weight / params.base_thruster_power, 0.01, params.max_thruster_power)
    binding = u.randint(0, NUM_THRUSTER_BINDINGS)

    t = sim.thrusters
    thrusters = dataclasses.replace(
        t,
        body=_set(t.body, slot, body, ok),
        anchor=_set(t.anchor, slot, anchor, ok),
        angle=_set(t.angle, slot, angle, ok),
        power=_set(t.power, slot, power, ok),
        active=_set(t.active, slot, True, ok),
    )
    level = dataclasses.replace(level, sim=dataclasses.replace(sim, thrusters=thrusters),
                                thruster_bindings=_set(level.thruster_bindings, slot, binding, ok))
    return level, ok
