"""Level file formats, and the plain description of a level that every format reads into and writes from.

Each format module turns a parsed JSON document into a `LevelSpec` (checking types and naming
the field path of every error) and a `LevelFile` back into a JSON document. `build` turns a
spec into arrays of a size class (checking geometry and capacities), `describe` turns a level
back into a spec. Keeping one in-between form means index fixing, recentring and mass
computation happen in exactly one place, for every format.

    file --format.read--> LevelSpec --build(size)--> LevelFile --describe--> LevelSpec --format.write--> file
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax.numpy as jnp
import numpy as np

from jax2d.geometry import GeometryError, circle_mass_properties, polygon_mass_properties, validate_polygon
from jax2d.state import COLLIDE_ALL, COLLIDE_NORMAL, COLLIDE_ONLY_ALL, Capacity, SimState, empty_state
from kinetix import ranges
from kinetix.formats.fields import f32
from kinetix.level import (
    NUM_MOTOR_BINDINGS,
    NUM_THRUSTER_BINDINGS,
    PHYSICS_PARAMS,
    ROLE_NAMES,
    Level,
    LevelError,
    LevelFile,
    LevelParams,
    SizeClass,
    size_for_counts,
)

# A polygon whose vertex centroid is further than this (relative to its size) from the body
# position is recentred on load. Below it the offset is float32 round-off of an already centred
# polygon, and leaving it alone is what makes load -> save -> load bitwise stable.
RECENTRE_TOLERANCE = 1e-6


@dataclasses.dataclass
class BodySpec:
    path: str  # where it came from, for error messages, e.g. "bodies[3]"
    shape: str  # "polygon" or "circle"
    position: tuple[float, float]
    angle: float = 0.0
    vertices: list | None = None  # polygons: counter-clockwise, body frame, relative to position
    radius: float | None = None  # circles
    fixed: bool = False
    role: int = 0
    density: float = 1.0
    friction: float = 1.0
    restitution: float = 0.0
    collision_mode: int = COLLIDE_NORMAL
    velocity: tuple[float, float] = (0.0, 0.0)
    angular_velocity: float = 0.0


@dataclasses.dataclass
class JointSpec:
    path: str
    a: int  # indices into LevelSpec.bodies
    b: int
    anchor_a: tuple[float, float]  # body frames, relative to the positions given in the spec
    anchor_b: tuple[float, float]
    ref_angle: float | None = None  # None: angle_b - angle_a as given
    fixed: bool = False
    motor_on: bool = False
    motor_speed: float = 1.0
    motor_power: float = 1.0
    motor_binding: int = 0
    motor_auto: bool = False
    limits: tuple[float, float] | None = None


@dataclasses.dataclass
class ThrusterSpec:
    path: str
    body: int  # index into LevelSpec.bodies
    anchor: tuple[float, float]  # body frame, relative to the body position given in the spec
    angle: float = 0.0  # direction of the force in the body frame
    power: float = 1.0
    binding: int = 0


@dataclasses.dataclass
class LevelSpec:
    bodies: list[BodySpec]
    joints: list[JointSpec]
    thrusters: list[ThrusterSpec]
    gravity: tuple[float, float] = (0.0, -9.81)
    params: LevelParams = LevelParams()
    size: SizeClass | None = None  # the size the file asks for; None: the smallest that fits
    name: str = ""
    warnings: list[str] = dataclasses.field(default_factory=list)
    # Where the file keeps a field, for error messages, keyed as kinetix.ranges.RANGES (e.g. "body.angle" ->
    # "rotation", "env.max_timesteps" -> "env_params.max_timesteps"); fields not listed use our format's names.
    field_names: dict[str, str | tuple[str, ...]] = dataclasses.field(default_factory=dict)


# ---------------------------------------------------------------- spec -> arrays


def _rotation(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def fit_errors(spec: LevelSpec, size: SizeClass) -> list[str]:
    """Why the spec does not fit the size class (empty if it does)."""
    counts = dict(
        polygons=sum(b.shape == "polygon" for b in spec.bodies),
        circles=sum(b.shape == "circle" for b in spec.bodies),
        joints=len(spec.joints),
        thrusters=len(spec.thrusters),
    )
    errors = [f"{n} {kind} > {getattr(size, kind)} allowed in size {size.name}"
              for kind, n in counts.items() if n > getattr(size, kind)]
    for body in spec.bodies:
        if body.shape == "polygon" and len(body.vertices) > size.max_vertices:
            errors.append(f"{body.path} has {len(body.vertices)} vertices > {size.max_vertices} allowed in "
                          f"size {size.name}")
    return errors


def smallest_size(spec: LevelSpec) -> SizeClass:
    polygons = [b for b in spec.bodies if b.shape == "polygon"]
    return size_for_counts(len(polygons), len(spec.bodies) - len(polygons), len(spec.joints), len(spec.thrusters),
                           max((len(b.vertices) for b in polygons), default=3))


@functools.cache
def _empty_state(capacity: Capacity) -> SimState:
    # Cached: JAX arrays are immutable, and building one costs more than everything else in a load.
    return empty_state(capacity)


def _numpy_arrays(struct) -> dict[str, np.ndarray]:
    return {f.name: np.array(getattr(struct, f.name)) for f in dataclasses.fields(struct)}


def _polygon(body: BodySpec, max_vertices: int) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(stored float32 vertices, body-frame shift of the position, mass, inertia) of a polygon body."""
    try:
        given = validate_polygon(body.vertices)
    except GeometryError as error:
        raise LevelError(f"{body.path}.vertices: {error}") from None
    _, _, centroid = polygon_mass_properties(given, 1.0)
    size = float(np.max(np.ptp(given, axis=0)))
    shift = centroid if np.linalg.norm(centroid) > RECENTRE_TOLERANCE * size else np.zeros(2)
    stored = (given - shift).astype(np.float32)
    try:
        # Mass from the stored float32 vertices, so that reloading a saved level recomputes it bitwise.
        mass, inertia, _ = polygon_mass_properties(stored.astype(np.float64), float(np.float32(body.density)))
    except GeometryError as error:
        raise LevelError(f"{body.path}.vertices: {error} (after rounding to float32)") from None
    padded = np.concatenate([stored, np.repeat(stored[-1:], max_vertices - len(stored), axis=0)])
    return padded, shift, mass, inertia


def _inverse_mass(body: BodySpec, mass: float, inertia: float) -> tuple[float, float]:
    """float32 (1 / mass, 1 / inertia) of a dynamic body; both must be finite and > 0 to simulate."""
    inverse = np.float32(1.0 / mass), np.float32(1.0 / inertia)
    if not all(np.isfinite(x) and x > 0 for x in inverse):
        raise LevelError(f"{body.path}: its mass {mass:.3g} kg and inertia {inertia:.3g} kg m^2 are outside what "
                         "float32 physics can simulate; change its size or density, or make it fixed")
    return inverse


def _check_body(body: BodySpec) -> None:
    """Values the model allows; formats check types and field presence before this."""
    if body.shape not in ("polygon", "circle"):
        raise LevelError(f"{body.path}.shape: expected polygon or circle, got {body.shape!r}")
    if body.collision_mode not in (COLLIDE_ONLY_ALL, COLLIDE_NORMAL, COLLIDE_ALL):
        raise LevelError(f"{body.path}.collision_mode: expected 0, 1 or 2, got {body.collision_mode}")
    if body.role not in range(len(ROLE_NAMES)):
        raise LevelError(f"{body.path}.role: expected 0..{len(ROLE_NAMES) - 1}, got {body.role}")
    if body.fixed and (body.velocity != (0.0, 0.0) or body.angular_velocity != 0.0):
        raise LevelError(f"{body.path}: a fixed body never moves, so it cannot have a velocity")


def build(spec: LevelSpec, size: SizeClass | None = None) -> LevelFile:
    """Arrays of `size` (default: the spec's own size, else the smallest that fits) holding the spec."""
    size = size or spec.size or smallest_size(spec)
    if errors := fit_errors(spec, size):
        raise LevelError("level does not fit: " + "; ".join(errors))
    check_references(spec)
    check_ranges(spec)
    sim = _empty_state(size.capacity)
    P, V = size.polygons, size.max_vertices
    b, j, t = _numpy_arrays(sim.bodies), _numpy_arrays(sim.joints), _numpy_arrays(sim.thrusters)
    roles = np.zeros(P + size.circles, np.int32)

    # Global slots: polygons first, then circles, each in spec order.
    slot_of, shift_of = [], []
    polygon_count = circle_count = 0
    for body in spec.bodies:
        if body.shape == "polygon":
            slot_of.append(polygon_count)
            polygon_count += 1
        else:
            slot_of.append(P + circle_count)
            circle_count += 1

    for body, i in zip(spec.bodies, slot_of, strict=True):
        _check_body(body)
        angle = float(np.float32(body.angle))
        position = np.array(body.position, np.float64)
        if body.shape == "polygon":
            b["vertices"][i], shift, mass, inertia = _polygon(body, V)
            b["n_vertices"][i] = len(body.vertices)
            position = position + _rotation(angle) @ shift
        else:
            radius = body.radius
            b["radius"][i - P] = radius
            mass, inertia, _ = circle_mass_properties(float(np.float32(radius)), float(np.float32(body.density)))
            shift = np.zeros(2)
        shift_of.append(shift)
        b["position"][i] = position
        b["angle"][i] = angle
        b["velocity"][i] = body.velocity
        b["angular_velocity"][i] = body.angular_velocity
        if not body.fixed:
            b["inv_mass"][i], b["inv_inertia"][i] = _inverse_mass(body, mass, inertia)
        b["density"][i] = body.density
        b["friction"][i] = body.friction
        b["restitution"][i] = body.restitution
        b["collision_mode"][i] = body.collision_mode
        b["active"][i] = True
        roles[i] = body.role

    warnings = list(spec.warnings)
    motor_bindings = np.zeros(size.joints, np.int32)
    motor_auto = np.zeros(size.joints, bool)
    for k, joint in enumerate(spec.joints):
        if joint.a == joint.b:
            raise LevelError(f"{joint.path}: a joint needs two different bodies, got body {joint.a} twice")
        a, c = spec.bodies[joint.a], spec.bodies[joint.b]
        # Not said of welds: a weld between two fixed parts is how a Kinetix export keeps a split fixed polygon one
        # group for collisions (a body jointed to one part collides with none of them; kinetix.formats.split).
        if a.fixed and c.fixed and not joint.fixed:
            warnings.append(f"{joint.path}: both bodies are fixed, so the joint does nothing")
        if joint.limits is not None and joint.limits[0] > joint.limits[1]:
            raise LevelError(f"{joint.path}.limits: lower {joint.limits[0]} is above upper {joint.limits[1]}")
        ref = joint.ref_angle if joint.ref_angle is not None else float(np.float32(c.angle)) - float(
            np.float32(a.angle))
        j["a"][k], j["b"][k] = slot_of[joint.a], slot_of[joint.b]
        j["anchor_a"][k] = np.asarray(joint.anchor_a) - shift_of[joint.a]
        j["anchor_b"][k] = np.asarray(joint.anchor_b) - shift_of[joint.b]
        j["ref_angle"][k] = ref
        j["active"][k] = True
        j["fixed"][k] = joint.fixed
        if not joint.fixed:  # a weld has no motor or limits: keep those fields at their empty values
            j["motor_on"][k] = joint.motor_on
            j["motor_speed"][k] = joint.motor_speed
            j["motor_power"][k] = joint.motor_power
            j["limit_on"][k] = joint.limits is not None
            j["lower"][k], j["upper"][k] = joint.limits or (0.0, 0.0)
            motor_bindings[k] = joint.motor_binding
            motor_auto[k] = joint.motor_auto

    thruster_bindings = np.zeros(size.thrusters, np.int32)
    for k, thruster in enumerate(spec.thrusters):
        t["body"][k] = slot_of[thruster.body]
        t["anchor"][k] = np.asarray(thruster.anchor) - shift_of[thruster.body]
        t["angle"][k] = thruster.angle
        t["power"][k] = thruster.power
        t["active"][k] = True
        thruster_bindings[k] = thruster.binding

    def as_jax(struct, arrays):
        return dataclasses.replace(struct, **{k: jnp.asarray(v) for k, v in arrays.items()})

    gravity = jnp.asarray([f32(spec.gravity[0]), f32(spec.gravity[1])], jnp.float32)
    sim = SimState(as_jax(sim.bodies, b), as_jax(sim.joints, j), as_jax(sim.thrusters, t), sim.contacts, gravity,
                   sim.frozen)
    level = Level(sim, jnp.asarray(roles), jnp.asarray(motor_bindings), jnp.asarray(motor_auto),
                  jnp.asarray(thruster_bindings))
    return LevelFile(level, spec.params, size, spec.name, warnings=tuple(warnings))


# ---------------------------------------------------------------- arrays -> spec


def describe(level: Level, params: LevelParams | None = None, name: str = "") -> LevelSpec:
    """The active entities of one (unbatched) level, polygons first then circles, as a spec of float32 values."""
    sim = level.sim
    if sim.bodies.active.ndim != 1:
        raise LevelError(f"expected one level, got a batch of shape {sim.bodies.active.shape[:-1]}")
    b = {f.name: np.asarray(getattr(sim.bodies, f.name)) for f in dataclasses.fields(sim.bodies)}
    P = sim.num_polygons
    roles = np.asarray(level.roles)
    active = np.nonzero(b["active"])[0]
    index_of = {int(i): k for k, i in enumerate(active)}
    bodies = []
    for k, i in enumerate(active):
        common = dict(
            path=f"bodies[{k}]",
            position=(f32(b["position"][i, 0]), f32(b["position"][i, 1])),
            angle=f32(b["angle"][i]),
            fixed=bool(b["inv_mass"][i] == 0),
            role=int(roles[i]),
            density=f32(b["density"][i]),
            friction=f32(b["friction"][i]),
            restitution=f32(b["restitution"][i]),
            collision_mode=int(b["collision_mode"][i]),
            velocity=(f32(b["velocity"][i, 0]), f32(b["velocity"][i, 1])),
            angular_velocity=f32(b["angular_velocity"][i]),
        )
        if i < P:
            n = int(b["n_vertices"][i])
            vertices = [[f32(x), f32(y)] for x, y in b["vertices"][i, :n]]
            bodies.append(BodySpec(shape="polygon", vertices=vertices, **common))
        else:
            bodies.append(BodySpec(shape="circle", radius=f32(b["radius"][i - P]), **common))

    def body_index(i, path):
        if int(i) not in index_of:
            raise LevelError(f"{path} is attached to body slot {int(i)}, which is not active")
        return index_of[int(i)]

    j = {f.name: np.asarray(getattr(sim.joints, f.name)) for f in dataclasses.fields(sim.joints)}
    bindings, auto = np.asarray(level.motor_bindings), np.asarray(level.motor_auto)
    joints = []
    for k, s in enumerate(np.nonzero(j["active"])[0]):
        path = f"joints[{k}]"
        joints.append(JointSpec(
            path=path,
            a=body_index(j["a"][s], path),
            b=body_index(j["b"][s], path),
            anchor_a=(f32(j["anchor_a"][s, 0]), f32(j["anchor_a"][s, 1])),
            anchor_b=(f32(j["anchor_b"][s, 0]), f32(j["anchor_b"][s, 1])),
            ref_angle=f32(j["ref_angle"][s]),
            fixed=bool(j["fixed"][s]),
            motor_on=bool(j["motor_on"][s]),
            motor_speed=f32(j["motor_speed"][s]),
            motor_power=f32(j["motor_power"][s]),
            motor_binding=int(bindings[s]),
            motor_auto=bool(auto[s]),
            limits=(f32(j["lower"][s]), f32(j["upper"][s])) if j["limit_on"][s] else None,
        ))

    t = {f.name: np.asarray(getattr(sim.thrusters, f.name)) for f in dataclasses.fields(sim.thrusters)}
    thruster_bindings = np.asarray(level.thruster_bindings)
    thrusters = []
    for k, s in enumerate(np.nonzero(t["active"])[0]):
        path = f"thrusters[{k}]"
        thrusters.append(ThrusterSpec(
            path=path,
            body=body_index(t["body"][s], path),
            anchor=(f32(t["anchor"][s, 0]), f32(t["anchor"][s, 1])),
            angle=f32(t["angle"][s]),
            power=f32(t["power"][s]),
            binding=int(thruster_bindings[s]),
        ))
    gravity = np.asarray(sim.gravity)
    return LevelSpec(bodies, joints, thrusters, (f32(gravity[0]), f32(gravity[1])), params or LevelParams(), None, name)


def check_references(spec: LevelSpec) -> None:
    """Body indices and binding values in range (formats check types; this checks what the model allows)."""
    n = len(spec.bodies)
    for joint in spec.joints:
        for side in ("a", "b"):
            if not 0 <= getattr(joint, side) < n:
                raise LevelError(f"{joint.path}.{side}: body {getattr(joint, side)} does not exist "
                                 f"(the level has {n} bodies)")
        if not 0 <= joint.motor_binding < NUM_MOTOR_BINDINGS:
            raise LevelError(f"{joint.path}: motor binding {joint.motor_binding} is not in [0, {NUM_MOTOR_BINDINGS})")
    for thruster in spec.thrusters:
        if not 0 <= thruster.body < n:
            raise LevelError(f"{thruster.path}.body: body {thruster.body} does not exist (the level has {n} bodies)")
        if not 0 <= thruster.binding < NUM_THRUSTER_BINDINGS:
            raise LevelError(f"{thruster.path}: thruster binding {thruster.binding} is not in "
                             f"[0, {NUM_THRUSTER_BINDINGS})")


def check_ranges(spec: LevelSpec) -> None:
    """Every numeric field of the spec within its range of kinetix.ranges.RANGES; LevelError names the field."""

    def check(key: str, value, path: str, ours: str) -> None:
        name = spec.field_names.get(key, ours)
        if isinstance(name, tuple):  # one file field per component (Kinetix joint limits)
            for part, x in zip(name, value, strict=True):
                ranges.check(key, x, f"{path}.{part}" if path else part)
        else:
            ranges.check(key, value, f"{path}.{name}" if path else name)

    p = spec.params
    for name in ("max_timesteps", "frame_skip", "dense_reward_scale"):
        check(f"env.{name}", getattr(p, name), "", f"env.{name}")
    for name in PHYSICS_PARAMS:
        check(f"env.physics.{name}", getattr(p, name), "", f"env.physics.{name}")
    check("gravity", spec.gravity, "", "gravity")
    for body in spec.bodies:
        for field in ("position", "angle", "density", "friction", "restitution", "velocity", "angular_velocity"):
            check(f"body.{field}", getattr(body, field), body.path, field)
        if body.shape == "polygon":
            check("body.vertices", body.vertices, body.path, "vertices")
        else:
            check("body.radius", body.radius, body.path, "radius")
    for joint in spec.joints:
        check("joint.anchor_a", joint.anchor_a, joint.path, "anchor_a")
        check("joint.anchor_b", joint.anchor_b, joint.path, "anchor_b")
        if joint.ref_angle is not None:
            check("joint.ref_angle", joint.ref_angle, joint.path, "ref_angle")
        if not joint.fixed:
            check("joint.motor.speed", joint.motor_speed, joint.path, "motor.speed")
            check("joint.motor.power", joint.motor_power, joint.path, "motor.power")
            if joint.limits is not None:
                check("joint.limits", joint.limits, joint.path, "limits")
    for thruster in spec.thrusters:
        for field in ("anchor", "angle", "power"):
            check(f"thruster.{field}", getattr(thruster, field), thruster.path, field)
