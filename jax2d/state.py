"""The simulation state: fixed-capacity arrays with `active` masks.

One scene is one `SimState`. Capacity (how many polygons, circles, joints and
thrusters fit) is given by the array shapes, so every scene of one size class
shares one compiled step and scenes batch under `vmap` by stacking.

Conventions
- Bodies have one global index: polygons first (0..P-1), then circles (P..P+C-1).
- A body's `position` is its centre of mass; polygon vertices are stored in the
  body frame relative to it, counter-clockwise (y up), padded past `n_vertices`.
- A body is static (fixed) when `inv_mass == 0`; static bodies never move.
- Joint and thruster anchors are in the body frame of the body they attach to.
- Angles are radians, counter-clockwise; units are SI (m, kg, s).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

# Collision modes (compatible with the public Kinetix files): two bodies collide
# iff either has mode COLLIDE_ALL, or both have a mode above COLLIDE_ONLY_ALL.
COLLIDE_ONLY_ALL = 0  # touches only bodies whose mode is COLLIDE_ALL (walls)
COLLIDE_NORMAL = 1
COLLIDE_ALL = 2


def modes_agree(mode_a, mode_b):
    """Whether bodies of these collision modes collide (the rule above), elementwise."""
    either_all = (mode_a == COLLIDE_ALL) | (mode_b == COLLIDE_ALL)
    return either_all | ((mode_a > COLLIDE_ONLY_ALL) & (mode_b > COLLIDE_ONLY_ALL))

# Columns of Joints.impulse, the accumulated impulses kept for warm starting.
J_LINEAR_X, J_LINEAR_Y, J_ANGULAR, J_MOTOR, J_LOWER, J_UPPER = range(6)
JOINT_IMPULSE_SIZE = 6


def _pytree(cls):
    """Register a dataclass whose every field is an array leaf."""
    cls = dataclasses.dataclass(frozen=True)(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    return jax.tree_util.register_dataclass(cls, data_fields=names, meta_fields=[])


@_pytree
class Bodies:
    """Rigid bodies, indexed globally (polygons then circles). Shapes: N = P + C."""

    position: jax.Array  # (N, 2) centre of mass, world frame
    angle: jax.Array  # (N,)
    velocity: jax.Array  # (N, 2) of the centre of mass
    angular_velocity: jax.Array  # (N,)
    inv_mass: jax.Array  # (N,) 0 for static bodies
    inv_inertia: jax.Array  # (N,) about the centre of mass; 0 for static bodies
    density: jax.Array  # (N,) kg/m^2, kept so edits can recompute mass
    friction: jax.Array  # (N,) combined per contact as sqrt(f_a * f_b)
    restitution: jax.Array  # (N,) combined per contact as max(e_a, e_b)
    collision_mode: jax.Array  # (N,) int32, see COLLIDE_*
    active: jax.Array  # (N,) bool
    vertices: jax.Array  # (P, V, 2) body frame, counter-clockwise, padded
    n_vertices: jax.Array  # (P,) int32 in [3, V]
    radius: jax.Array  # (C,) circle radii


@_pytree
class Joints:
    """Revolute and fixed (weld) joints between two bodies a and b. Shape: J."""

    a: jax.Array  # (J,) int32 global body index
    b: jax.Array  # (J,) int32 global body index
    anchor_a: jax.Array  # (J, 2) anchor in a's body frame
    anchor_b: jax.Array  # (J, 2) anchor in b's body frame
    ref_angle: jax.Array  # (J,) angle_b - angle_a when the joint was made
    active: jax.Array  # (J,) bool
    fixed: jax.Array  # (J,) bool: weld (locks relative rotation too)
    motor_on: jax.Array  # (J,) bool
    motor_speed: jax.Array  # (J,) target d(angle_b - angle_a)/dt at action 1, in units of params.base_motor_speed
    motor_power: jax.Array  # (J,) max relative angular acceleration, in units of params.base_motor_power
    limit_on: jax.Array  # (J,) bool
    lower: jax.Array  # (J,) lower limit of angle_b - angle_a - ref_angle
    upper: jax.Array  # (J,) upper limit
    impulse: jax.Array  # (J, 6) accumulated impulses for warm starting (J_* columns)


@_pytree
class Thrusters:
    """A force at a point of a body along a direction fixed in that body. Shape: T."""

    body: jax.Array  # (T,) int32 global body index
    anchor: jax.Array  # (T, 2) point of application in the body frame
    angle: jax.Array  # (T,) direction of the force in the body frame
    power: jax.Array  # (T,) force at action 1, in units of params.base_thruster_power
    active: jax.Array  # (T,) bool


@_pytree
class Contacts:
    """Persistent contact data, one row per static pair slot (see pairs.py), 2 points each."""

    normal_impulse: jax.Array  # (S, 2) accumulated, for warm starting
    tangent_impulse: jax.Array  # (S, 2)
    key: jax.Array  # (S, 2) int32 feature key; warm start only when it matches
    active: jax.Array  # (S, 2) bool: the point existed in the last step (within the speculative distance)
    separation: jax.Array  # (S, 2) its separation at the start of the last step (negative = overlap); 0 if inactive


@_pytree
class SimState:
    bodies: Bodies
    joints: Joints
    thrusters: Thrusters
    contacts: Contacts
    gravity: jax.Array  # (2,)
    # () int32: how many bodies the step that made this state froze because their result was not finite
    # (step._store's guard keeps their old pose and stops them). 0 in a healthy run; tests assert it.
    frozen: jax.Array

    @property
    def num_polygons(self) -> int:
        return self.bodies.vertices.shape[-3]

    @property
    def num_circles(self) -> int:
        return self.bodies.radius.shape[-1]

    @property
    def num_bodies(self) -> int:
        return self.num_polygons + self.num_circles

    @property
    def num_joints(self) -> int:
        return self.joints.a.shape[-1]

    @property
    def num_thrusters(self) -> int:
        return self.thrusters.body.shape[-1]

    @property
    def max_vertices(self) -> int:
        return self.bodies.vertices.shape[-2]


@dataclasses.dataclass(frozen=True)
class Capacity:
    """How many entities a scene can hold. Hashable, so it can be a static argument."""

    polygons: int = 12
    circles: int = 4
    joints: int = 6
    thrusters: int = 2
    max_vertices: int = 8

    def __post_init__(self):
        for name in ("polygons", "circles", "joints", "thrusters"):
            if getattr(self, name) < 0:
                raise ValueError(f"capacity {name} must be >= 0, got {getattr(self, name)}")
        if not 3 <= self.max_vertices <= 8:
            raise ValueError(f"max_vertices must be in [3, 8], got {self.max_vertices}")
        if self.polygons + self.circles < 1:
            raise ValueError("a scene needs room for at least one body")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SimParams:
    """Runtime physics parameters (traced, so they can differ per batch element)."""

    dt: float | jax.Array = 1.0 / 60.0
    # Soft contact (Box2D v3 "soft step"): stiffness in Hz and damping ratio.
    contact_hertz: float | jax.Array = 60.0
    contact_damping_ratio: float | jax.Array = 10.0
    joint_hertz: float | jax.Array = 60.0
    joint_damping_ratio: float | jax.Array = 0.7  # see docs/engine.md: 2 (Box2D's) rang on spinning welded clusters
    max_push_velocity: float | jax.Array = 3.0  # m/s cap on overlap recovery speed
    speculative_distance: float | jax.Array = 0.04  # m; contact points are kept this far apart
    linear_slop: float | jax.Array = 0.005  # m of allowed overlap
    restitution_threshold: float | jax.Array = 0.5  # m/s; slower impacts do not bounce
    max_linear_speed: float | jax.Array = 100.0  # m/s clamp; a guard, not physics
    max_angular_speed: float | jax.Array = 100.0  # rad/s clamp
    max_position: float | jax.Array = 1000.0  # m; positions are clipped to +-this
    # Actuator scales (the public Kinetix uses 6 rad/s, 900 rad/s^2 and 10 N).
    base_motor_speed: float | jax.Array = 6.0
    base_motor_power: float | jax.Array = 900.0
    base_thruster_power: float | jax.Array = 10.0


CONTROL_FLOWS = ("skip", "fixed")  # SolverConfig.control_flow


@dataclasses.dataclass(frozen=True)
class SolverConfig:
    """Compile-time solver settings (static: changing them recompiles)."""

    substeps: int = 4
    relax_iterations: int = 1
    # More passes per substep over only the contact points stiffened by their load (a heavy body on a light
    # one: contact_solver.load_softness), after the solve and after the relax_iterations over all. Steps without
    # such a point in any scene of the batch skip them (sweeps.schedule). The 100:1 stacks of
    # tests/jax2d/mass_ratio.py, largest overlap over 10 s on the slab / the levels' floor (mm): 4 relax passes
    # 4.95 / 8.9 (the stack on the levels' floor rocked and a 50 mm offset one slid 102 mm off), 8 relax 4.9 / 6.1;
    # 2 solve + 1 relax 5.2 / 5.3 (all within 6.2 mm of where they were put), 1 + 1 5.4 / 6.9, 2 + 0 5.6 / 5.9.
    stiff_solve_iterations: int = 2
    stiff_relax_iterations: int = 1
    warm_start: bool = True
    # The joint projection stage (step.py, joint_block.py) at the end of each step: velocities
    # are made to satisfy every joint exactly, closing this fraction of each joint's position
    # error per step. None skips the stage.
    joint_projection: float | None = 0.2
    # The same stage's position part: this fraction of each joint's position error is removed by
    # moving the bodies (up to a cap per step, joint_solver.MAX_SHIFT / MAX_TURN), without changing
    # velocities. None skips it; it needs joint_projection.
    joint_position_projection: float | None = 1.0
    # The restitution stage (restitution.py): sweeps that propagate an impact through chains of touching
    # bodies (a chain of n bodies needs n - 1 in the worst colour order: 2 covers a three-ball cradle), then
    # sweeps that make the bounces. Each sweep runs only in steps where some scene of the batch bounces; the
    # three-ball cradle and the bounce tests came out the same with 3 and 6 (1.000, (0, 0, 3)).
    impact_sweeps: int = 2
    bounce_sweeps: int = 2
    # The first `num_static` polygons are always static (the public Kinetix walls), a promise
    # the caller keeps: pairs among them are never checked, and the contact sweeps may visit
    # them in several slots of one colour (pairs.wall_grouped), which is wrong for a moving body.
    num_static: int = 0
    # Batches larger than this are stepped in equal parts of at most this many scenes, one part
    # after the other, so each part's constraint data stays in the CPU's cache (step.step_batch).
    chunk: int = 256
    # Big scenes: a broad phase picks the pairs whose bounding boxes overlap, and only those are
    # collided and solved, coloured per scene in the step (jax2d.broad_phase). None: on for scenes of
    # more than broad_phase.AUTO_BODIES bodies (the xl class), at any batch; True / False force it.
    broad_phase: bool | None = None
    # The static-walls stages after the joint projection (jax2d/static_walls.py): fast bodies swept back to
    # where they enter a static body, and bodies pushed out of static ones. False skips both (to measure them).
    static_walls: bool = True
    # How the step's loops and skips are compiled (jax2d/control.py). "skip": loops visit only the colours and
    # joint slots live in some scene of the batch, and stages nobody in the batch needs are skipped by a
    # conditional: the least work. "fixed": every loop runs its full static count and nothing is skipped by a
    # conditional, so no trip count or predicate is read from the data. Both give the same results to rounding
    # (solving an empty colour or an inactive joint changes nothing). Skip was faster on the CPU and on an H200
    # (control.py has the measurements), so it is the default everywhere; fixed stays to measure on new hardware.
    control_flow: str = "skip"

    def __post_init__(self):
        if self.control_flow not in CONTROL_FLOWS:
            raise ValueError(f"control_flow must be one of {', '.join(CONTROL_FLOWS)}, not {self.control_flow!r}")
        if self.stiff_relax_iterations and not self.relax_iterations:
            raise ValueError("stiff_relax_iterations are more passes after the relax pass: they need "
                             "relax_iterations >= 1")
        if self.joint_position_projection is not None and self.joint_projection is None:
            raise ValueError("joint_position_projection is a part of the joint projection stage: it needs "
                             "joint_projection (set both to None to skip the stage)")


def empty_state(capacity: Capacity, gravity=(0.0, -9.81)) -> SimState:
    """A scene with every slot inactive."""
    from jax2d.pairs import contact_layout

    P, C, J, T, V = capacity.polygons, capacity.circles, capacity.joints, capacity.thrusters, capacity.max_vertices
    N = P + C
    f = jnp.float32
    bodies = Bodies(
        position=jnp.zeros((N, 2), f),
        angle=jnp.zeros((N,), f),
        velocity=jnp.zeros((N, 2), f),
        angular_velocity=jnp.zeros((N,), f),
        inv_mass=jnp.zeros((N,), f),
        inv_inertia=jnp.zeros((N,), f),
        density=jnp.ones((N,), f),
        friction=jnp.ones((N,), f),
        restitution=jnp.zeros((N,), f),
        collision_mode=jnp.ones((N,), jnp.int32),
        active=jnp.zeros((N,), bool),
        vertices=jnp.zeros((P, V, 2), f),
        n_vertices=jnp.full((P,), 4, jnp.int32) if V >= 4 else jnp.full((P,), V, jnp.int32),
        radius=jnp.zeros((C,), f),
    )
    joints = Joints(
        a=jnp.zeros((J,), jnp.int32),
        b=jnp.zeros((J,), jnp.int32),
        anchor_a=jnp.zeros((J, 2), f),
        anchor_b=jnp.zeros((J, 2), f),
        ref_angle=jnp.zeros((J,), f),
        active=jnp.zeros((J,), bool),
        fixed=jnp.zeros((J,), bool),
        motor_on=jnp.zeros((J,), bool),
        motor_speed=jnp.zeros((J,), f),
        motor_power=jnp.zeros((J,), f),
        limit_on=jnp.zeros((J,), bool),
        lower=jnp.zeros((J,), f),
        upper=jnp.zeros((J,), f),
        impulse=jnp.zeros((J, JOINT_IMPULSE_SIZE), f),
    )
    thrusters = Thrusters(
        body=jnp.zeros((T,), jnp.int32),
        anchor=jnp.zeros((T, 2), f),
        angle=jnp.zeros((T,), f),
        power=jnp.zeros((T,), f),
        active=jnp.zeros((T,), bool),
    )
    S = contact_layout(P, C).num_slots
    contacts = Contacts(
        normal_impulse=jnp.zeros((S, 2), f),
        tangent_impulse=jnp.zeros((S, 2), f),
        key=jnp.full((S, 2), -1, jnp.int32),
        active=jnp.zeros((S, 2), bool),
        separation=jnp.zeros((S, 2), f),
    )
    return SimState(bodies, joints, thrusters, contacts, jnp.asarray(gravity, f), jnp.zeros((), jnp.int32))
