"""What the agent sees of a level: "entity" (default), "flat" or "pixels". Pure jnp; jit and vmap freely.

Every feature is float32, finite (nan_to_num) and clipped to [-OBS_CLIP, OBS_CLIP]; rows of inactive
slots are all zero. Angles are radians, positions metres in the world frame, anchors and vertices
in the frame of the body they belong to (relative to its centre of mass).

Entity observation: a dict of
    polygons (P, 22 + 2V + (V-2))   circles (C, 23)      joints (2J, 23)      thrusters (T, 8)
    polygon_mask (P,) circle_mask (C,) joint_mask (2J,) thruster_mask (T,)  (bool, slot is active)
    joint_indexes (2J, 2) int32: global body indices (from, to) of each joint row
    thruster_indexes (T,) int32: global body index of each thruster
    attention_mask (4, N, N) bool over global body indices (polygons then circles):
        0 both bodies active; 1 connected through any chain of active joints; 2 directly jointed;
        3 touching (jax2d.touching.touching_matrix). Every active body also attends to itself in all four,
        so no attention row is empty.

Body columns (polygons and circles share 0-21):
    0-1 position            2-3 velocity            4 log(1 + inverse mass) 5 log(1 + inverse inertia)
    6 density               7 tanh(angular velocity / 10)                   8-11 role one-hot (none, green, blue, red)
    12-13 sin, cos of angle 14 friction             15 restitution          16 is fixed (inverse mass 0)
    17-19 collision mode one-hot (COLLIDE_ONLY_ALL, NORMAL, ALL)            20-21 gravity
  polygons then: 22..22+2V-1 vertices (x, y) x V, zero past n_vertices; then V-2 columns: n_vertices one-hot (3..V)
  circles then:  22 radius

Joint columns. Row j describes joint j seen from body a (from = a, to = b), row J + j the same joint seen
from body b, so each row reads in its own from-body's terms: theta = angle_to - angle_from - ref, with
ref the joint's reference angle (negated in the reversed row), motor speed and limits likewise.
    0 active    1 is fixed (weld)    2-3 anchor in the from-body frame    4-5 anchor in the to-body frame
    6-7 sin, cos of theta    8 motor on    9 motor speed    10 motor power    11 limit on
    12-13 sin, cos of lower limit    14-15 sin, cos of upper limit    16 lower - theta    17 upper - theta
    18-21 motor binding one-hot    22 motor auto
  Motor columns (8-10, 18-22) are zero unless the motor is on, limit columns (11-17) unless limits are on,
  and both for welds.

Thruster columns: 0 active    1-2 anchor (body frame)    3-4 sin, cos of the direction (body frame)
    5 power    6-7 thruster binding one-hot

Flat observation: one vector, in this order, of
    per body slot (polygons then circles): [active, body columns 0-19, the polygon or circle columns]
    per joint slot (the a -> b row only): [joint columns, one-hot(a, N), one-hot(b, N)]
    per thruster slot: [thruster columns, one-hot(body, N)]
    gravity (2)
  so its length is P(21 + 2V + V - 2) + C(22) + J(23 + 2N) + T(8 + N) + 2 (see flat_size):
  s 313, m 442, l 984 with V = 8.

Pixel observation: kinetix.render.render_pixels(level, resolution), an RGB (res, res, 3) float32 image in [0, 1].
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jax2d.state import SimState
from jax2d.touching import touching_matrix
from kinetix.geometry import groups_from_joints
from kinetix.level import NUM_MOTOR_BINDINGS, NUM_THRUSTER_BINDINGS, Level, SizeClass

OBSERVATION_TYPES = ("entity", "flat", "pixels")
# As the public Kinetix flat observation. Inverse masses and inertias enter as log(1 + x): raw, an ordinary
# 0.6 m x 0.4 m box has inverse inertia 48 and a 10 cm ball 6000, far beyond any clip that keeps the rest readable.
OBS_CLIP = 10.0

BODY_FEATURES = 22  # shared columns, gravity included
CIRCLE_FEATURES = BODY_FEATURES + 1
JOINT_FEATURES = 23
THRUSTER_FEATURES = 8
NUM_ROLES = 4
NUM_COLLISION_MODES = 3


def polygon_features(max_vertices: int) -> int:
    return BODY_FEATURES + 2 * max_vertices + (max_vertices - 2)


def flat_size(size: SizeClass) -> int:
    """Length of the flat observation of a size class."""
    P, C, J, T, V = size.polygons, size.circles, size.joints, size.thrusters, size.max_vertices
    N = P + C
    body_without_gravity = BODY_FEATURES - 2
    return (P * (1 + body_without_gravity + 2 * V + V - 2) + C * (1 + body_without_gravity + 1)
            + J * (JOINT_FEATURES + 2 * N) + T * (THRUSTER_FEATURES + N) + 2)


def check_observation_type(kind: str) -> str:
    if kind not in OBSERVATION_TYPES:
        raise ValueError(f"unknown observation type {kind!r}: use one of {', '.join(OBSERVATION_TYPES)}")
    return kind


def _finite(x: jax.Array) -> jax.Array:
    return jnp.clip(jnp.nan_to_num(x.astype(jnp.float32), posinf=OBS_CLIP, neginf=-OBS_CLIP), -OBS_CLIP, OBS_CLIP)


def _f(x) -> jax.Array:
    return jnp.asarray(x, jnp.float32)


def _body_columns(level: Level) -> jax.Array:
    """(N, 20): body columns 0-19 (everything but gravity)."""
    b = level.sim.bodies
    return jnp.concatenate([
        b.position, b.velocity, jnp.log1p(jnp.maximum(b.inv_mass, 0.0))[:, None],
        jnp.log1p(jnp.maximum(b.inv_inertia, 0.0))[:, None], b.density[:, None],
        jnp.tanh(b.angular_velocity / 10.0)[:, None],
        jax.nn.one_hot(level.roles, NUM_ROLES),
        jnp.sin(b.angle)[:, None], jnp.cos(b.angle)[:, None],
        b.friction[:, None], b.restitution[:, None], _f(b.inv_mass == 0)[:, None],
        jax.nn.one_hot(b.collision_mode, NUM_COLLISION_MODES),
    ], axis=-1)


def _polygon_shape(sim: SimState) -> jax.Array:
    """(P, 2V + V - 2): vertices zero-padded past n_vertices, then n_vertices one-hot over 3..V."""
    b = sim.bodies
    P, V = sim.num_polygons, sim.max_vertices
    used = jnp.arange(V)[None, :] < b.n_vertices[:, None]
    vertices = jnp.where(used[..., None], b.vertices, 0.0).reshape(P, 2 * V)
    return jnp.concatenate([vertices, jax.nn.one_hot(b.n_vertices - 3, V - 2)], axis=-1)


def _joint_rows(level: Level) -> jax.Array:
    """(2J, 23): joint columns for the a -> b rows, then the b -> a rows."""
    j, b = level.sim.joints, level.sim.bodies
    theta = b.angle[j.b] - b.angle[j.a] - j.ref_angle

    def rows(anchor_from, anchor_to, theta, sign, lower, upper):
        motor = _f(j.motor_on & ~j.fixed)[:, None]
        limit = _f(j.limit_on & ~j.fixed)[:, None]
        motor_part = jnp.concatenate([_f(j.motor_on)[:, None], (sign * j.motor_speed)[:, None], j.motor_power[:, None]],
                                     axis=-1)
        limit_part = jnp.stack([_f(j.limit_on), jnp.sin(lower), jnp.cos(lower), jnp.sin(upper), jnp.cos(upper),
                                lower - theta, upper - theta], axis=-1)
        binding_part = jnp.concatenate([jax.nn.one_hot(level.motor_bindings, NUM_MOTOR_BINDINGS),
                                        _f(level.motor_auto)[:, None]], axis=-1)
        out = jnp.concatenate([
            _f(j.active)[:, None], _f(j.fixed)[:, None], anchor_from, anchor_to,
            jnp.sin(theta)[:, None], jnp.cos(theta)[:, None],
            motor_part * motor, limit_part * limit, binding_part * motor,
        ], axis=-1)
        return out * _f(j.active)[:, None]

    forward = rows(j.anchor_a, j.anchor_b, theta, 1.0, j.lower, j.upper)
    backward = rows(j.anchor_b, j.anchor_a, -theta, -1.0, -j.upper, -j.lower)
    return jnp.concatenate([forward, backward], axis=0)


def _thruster_rows(level: Level) -> jax.Array:
    """(T, 8)."""
    t = level.sim.thrusters
    out = jnp.concatenate([
        _f(t.active)[:, None], t.anchor, jnp.sin(t.angle)[:, None], jnp.cos(t.angle)[:, None], t.power[:, None],
        jax.nn.one_hot(level.thruster_bindings, NUM_THRUSTER_BINDINGS),
    ], axis=-1)
    return out * _f(t.active)[:, None]


def attention_masks(level: Level) -> jax.Array:
    """(4, N, N) bool: all active, joint-chain connected, directly jointed, touching (self always included)."""
    sim = level.sim
    N = sim.num_bodies
    active = sim.bodies.active
    j = sim.joints
    # Directly jointed: one comparison per (joint, body, body), reduced over the joints. Chains of joints: equal
    # joint groups (kinetix.geometry.groups_from_joints). As matrix products (a one-hot product, then log2 N
    # squarings) they made env rollouts that keep the observation 10 % slower at s, batch 256 (docs/engine.md,
    # "The observation's masks").
    body = jnp.arange(N)
    link = jnp.any(j.active[:, None, None] & (j.a[:, None, None] == body[:, None]) & (j.b[:, None, None] == body),
                   axis=0)
    link = link | link.T
    eye = jnp.eye(N, dtype=bool)
    groups = groups_from_joints(j.a, j.b, j.active, N)
    reach = groups[:, None] == groups[None, :]  # each body with itself too
    pair = active[:, None] & active[None, :]
    touching = touching_matrix(sim)
    return jnp.stack([pair, reach & pair, (link | eye) & pair, (touching | eye) & pair])


def entity_observation(level: Level) -> dict[str, jax.Array]:
    sim = level.sim
    P = sim.num_polygons
    active = sim.bodies.active
    gravity = jnp.broadcast_to(sim.gravity, (sim.num_bodies, 2))
    body = jnp.concatenate([_body_columns(level), gravity], axis=-1)
    polygons = jnp.concatenate([body[:P], _polygon_shape(sim)], axis=-1)
    circles = jnp.concatenate([body[P:], sim.bodies.radius[:, None]], axis=-1)
    j = sim.joints
    return {
        "polygons": _finite(polygons * _f(active[:P])[:, None]),
        "circles": _finite(circles * _f(active[P:])[:, None]),
        "joints": _finite(_joint_rows(level)),
        "thrusters": _finite(_thruster_rows(level)),
        "polygon_mask": active[:P],
        "circle_mask": active[P:],
        "joint_mask": jnp.concatenate([j.active, j.active]),
        "thruster_mask": sim.thrusters.active,
        "joint_indexes": jnp.concatenate([jnp.stack([j.a, j.b], -1), jnp.stack([j.b, j.a], -1)]).astype(jnp.int32),
        "thruster_indexes": sim.thrusters.body.astype(jnp.int32),
        "attention_mask": attention_masks(level),
    }


def flat_observation(level: Level) -> jax.Array:
    sim = level.sim
    P, N, J = sim.num_polygons, sim.num_bodies, sim.num_joints
    active = _f(sim.bodies.active)[:, None]
    body = jnp.concatenate([active, _body_columns(level)], axis=-1) * active
    polygons = jnp.concatenate([body[:P], _polygon_shape(sim) * active[:P]], axis=-1)
    circles = jnp.concatenate([body[P:], sim.bodies.radius[:, None] * active[P:]], axis=-1)
    j, t = sim.joints, sim.thrusters
    joints = jnp.concatenate([_joint_rows(level)[:J], jax.nn.one_hot(j.a, N), jax.nn.one_hot(j.b, N)], axis=-1)
    joints = joints * _f(j.active)[:, None]
    thrusters = jnp.concatenate([_thruster_rows(level), jax.nn.one_hot(t.body, N)], axis=-1) * _f(t.active)[:, None]
    parts = [polygons, circles, joints, thrusters, sim.gravity[None, :]]
    return _finite(jnp.concatenate([p.reshape(-1) for p in parts]))


def pixel_observation(level: Level, resolution: int) -> jax.Array:
    from kinetix.render import render_pixels  # written separately; imported only when pixels are asked for

    return jnp.asarray(render_pixels(level, resolution), jnp.float32)


def observe(level: Level, kind: str = "entity", pixel_resolution: int = 64):
    """The observation of `level` of type `kind` ("entity", "flat" or "pixels")."""
    check_observation_type(kind)
    if kind == "entity":
        return entity_observation(level)
    if kind == "flat":
        return flat_observation(level)
    return pixel_observation(level, pixel_resolution)
