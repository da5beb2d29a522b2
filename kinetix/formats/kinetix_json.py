"""The public Kinetix level JSON: import and export (see docs/level-format.md for the field mapping).

Their files hold the whole fixed-capacity state: `env_state` with every slot of `polygon`,
`circle`, `joint` and `thruster` (inactive ones too), plus `env_params` and `static_env_params`.
Vectors are dicts keyed "0", "1", ...; arrays may be plain lists or such dicts, and both are
accepted. Their polygon vertices are clockwise (ours are counter-clockwise) and their joints
and thrusters name bodies by global index with THEIR polygon count (polygons, then circles).

Import keeps only active entities; fields we do not use are ignored (their files carry solver
caches and settings of their engine). Export writes a file shaped like theirs: padded to the
size class, walls in polygon slots 0-3, zeroed solver caches, a recomputed collision matrix.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np

from kinetix.formats import BodySpec, JointSpec, LevelSpec, ThrusterSpec, build, describe, fit_errors
from kinetix.formats.fields import Fields, check_vector
from kinetix.formats.split import MAX_PART_VERTICES, Split, split_polygons
from kinetix.level import (
    MAX_BODIES,
    MAX_JOINTS,
    MAX_THRUSTERS,
    NUM_MOTOR_BINDINGS,
    NUM_THRUSTER_BINDINGS,
    NUM_WALLS,
    ROLE_NAMES,
    SIZES,
    LevelError,
    LevelFile,
    LevelParams,
    SizeClass,
    size_class,
)

# Their loader builds an empty scene whose every polygon holds the 4-vertex floor and then writes each file slot
# into it, so it opens only files whose `static_env_params.max_polygon_vertices` is 4 (any other value fails with
# "Incompatible shapes for broadcasting"), and their collision code reads only vertex slots 0-3. Export always
# writes 4 and cuts bigger polygons into welded parts (kinetix.formats.split).
KINETIX_MAX_VERTICES = MAX_PART_VERTICES
# The size classes of the public Kinetix (its env_size configs), smallest first. It also loads files of any other
# capacities (env_size custom reads them from the file).
PUBLIC_SIZES = ("s", "m", "l")

# Their engine settings that we do not model, written on export with the values of their level files.
_THEIR_SOLVER_PARAMS = dict(
    slop=0.01,
    baumgarte_coefficient_joints_v=2.0,
    baumgarte_coefficient_joints_p=0.7,
    baumgarte_coefficient_fjoint_av=2.0,
    baumgarte_coefficient_rjoint_limit_av=5.0,
    baumgarte_coefficient_collision=0.2,
    joint_stiffness=0.6,
    clip_position=15,
    clip_velocity=100,
    clip_angular_velocity=50,
)
_THEIR_MOTOR_PARAMS = dict(motor_decay_coefficient=0.1, motor_joint_limit=0.1, base_friction=0.4)

# Their names for the fields that kinetix.ranges bounds, so a range error names the field as it is in the file
# (vertex indices in such errors count in our counter-clockwise order).
_FIELD_NAMES: dict[str, str | tuple[str, ...]] = {
    "env.max_timesteps": "env_params.max_timesteps",
    "env.frame_skip": "static_env_params.frame_skip",
    "env.dense_reward_scale": "env_params.dense_reward_scale",
    "env.physics.dt": "env_params.dt",
    "env.physics.base_motor_speed": "env_params.base_motor_speed",
    "env.physics.base_motor_power": "env_params.base_motor_power",
    "env.physics.base_thruster_power": "env_params.base_thruster_power",
    "gravity": "env_state.gravity",
    "body.angle": "rotation",
    "joint.anchor_a": "a_relative_pos",
    "joint.anchor_b": "b_relative_pos",
    "joint.ref_angle": "rotation",
    "joint.motor.speed": "motor_speed",
    "joint.motor.power": "motor_power",
    "joint.limits": ("min_rotation", "max_rotation"),
    "thruster.anchor": "relative_position",
    "thruster.angle": "rotation",
}


# ---------------------------------------------------------------- import


def read(data) -> LevelSpec:
    top = Fields(data, "", lists_may_be_dicts=True)
    top.require("env_state")
    state = top.child("env_state")
    state.require("polygon", "circle")
    polygons, circles = state.list("polygon"), state.list("circle")
    joints, thrusters = state.list("joint", []), state.list("thruster", [])
    warnings: list[str] = []

    # Global index in the file (their polygon count) -> index among the imported (active) bodies.
    bodies: list[BodySpec] = []
    index_of: dict[int, int] = {}
    for shape, items, first in (("polygon", polygons, 0), ("circle", circles, len(polygons))):
        for k, item in enumerate(items):
            fields = Fields(item, f"env_state.{shape}[{k}]", lists_may_be_dicts=True)
            if fields.boolean("active"):
                index_of[first + k] = len(bodies)
                bodies.append(_read_body(fields, shape, warnings))
    num_slots = len(polygons) + len(circles)

    def body_ref(fields: Fields, key: str) -> int | None:
        g = fields.integer(key, low=0)
        if g >= num_slots:
            raise LevelError(f"{fields.where(key)}: {g} is not a body (the file has {num_slots} body slots)")
        if g not in index_of:
            warnings.append(f"{fields.path}: dropped, it is attached to inactive body {g} and has no effect")
            return None
        return index_of[g]

    joint_specs = []
    for k, item in enumerate(joints):
        fields = Fields(item, f"env_state.joint[{k}]", lists_may_be_dicts=True)
        if fields.boolean("active"):
            fields.require("a_index", "b_index", "a_relative_pos", "b_relative_pos")
            a, b = body_ref(fields, "a_index"), body_ref(fields, "b_index")
            if a is not None and b is not None:
                joint_specs.append(_read_joint(fields, a, b, fields.path))
    thruster_specs = []
    for k, item in enumerate(thrusters):
        fields = Fields(item, f"env_state.thruster[{k}]", lists_may_be_dicts=True)
        if fields.boolean("active"):
            fields.require("object_index", "relative_position")
            body = body_ref(fields, "object_index")
            if body is not None:
                thruster_specs.append(ThrusterSpec(
                    path=fields.path,
                    body=body,
                    anchor=fields.vector("relative_position"),
                    angle=fields.number("rotation", 0.0),
                    power=fields.number("power", 1.0),
                    binding=fields.integer("thruster_binding", 0, low=0, high=NUM_THRUSTER_BINDINGS - 1),
                ))

    env = top.child("env_params", {})
    static = top.child("static_env_params", {})
    defaults = LevelParams()
    params = LevelParams(
        max_timesteps=env.integer("max_timesteps", defaults.max_timesteps),
        frame_skip=static.integer("frame_skip", defaults.frame_skip),
        dense_reward_scale=env.number("dense_reward_scale", defaults.dense_reward_scale),
        dt=env.number("dt", defaults.dt),
        base_motor_speed=env.number("base_motor_speed", defaults.base_motor_speed),
        base_motor_power=env.number("base_motor_power", defaults.base_motor_power),
        base_thruster_power=env.number("base_thruster_power", defaults.base_thruster_power),
    )
    counts = dict(polygons=len(polygons), circles=len(circles), joints=len(joints), thrusters=len(thrusters))
    declared = {kind: static.data.get(f"num_{kind}") for kind in counts}
    if any(value is not None and value != counts[kind] for kind, value in declared.items()):
        warnings.append(f"static_env_params capacities {declared} differ from the array lengths {counts}; "
                        "using the array lengths")
    return LevelSpec(
        bodies=bodies,
        joints=joint_specs,
        thrusters=thruster_specs,
        gravity=state.vector("gravity", [0.0, -9.81]),
        params=params,
        size=_size_for(counts),
        warnings=warnings,
        field_names=dict(_FIELD_NAMES),
    )


def _size_for(counts: dict[str, int]) -> SizeClass:
    for size in SIZES.values():
        if size.counts() == counts:
            return size
    return SizeClass("custom", **counts)


def _read_body(fields: Fields, shape: str, warnings: list[str]) -> BodySpec:
    fields.require("position", "inverse_mass", *(("n_vertices", "vertices") if shape == "polygon" else ("radius",)))
    fixed = fields.number("inverse_mass", low=0.0) == 0.0
    spec = BodySpec(
        path=fields.path,
        shape=shape,
        position=fields.vector("position"),
        angle=fields.number("rotation", 0.0),
        fixed=fixed,
        role=fields.integer("role", 0, low=0, high=len(ROLE_NAMES) - 1),
        density=fields.number("density", 1.0),
        friction=fields.number("friction", 1.0),
        restitution=fields.number("restitution", 0.0),
        collision_mode=fields.integer("collision_mode", 1, low=0, high=2),
        velocity=fields.vector("velocity", [0.0, 0.0]),
        angular_velocity=fields.number("angular_velocity", 0.0),
    )
    if fixed and (spec.velocity != (0.0, 0.0) or spec.angular_velocity != 0.0):
        warnings.append(f"{fields.path}: velocity of a fixed body set to zero (fixed bodies never move)")
        spec.velocity, spec.angular_velocity = (0.0, 0.0), 0.0
    if shape == "polygon":
        n = fields.integer("n_vertices", low=3, high=8)
        vertices = fields.list("vertices")
        if len(vertices) < n:
            raise LevelError(f"{fields.where('vertices')}: n_vertices is {n} but only {len(vertices)} are given")
        where = fields.where("vertices")
        points = [fields.list_value(v, f"{where}[{i}]") for i, v in enumerate(vertices[:n])]
        spec.vertices = [check_vector(p, f"{where}[{i}]") for i, p in enumerate(points)][::-1]  # clockwise -> ccw
    else:
        spec.radius = fields.number("radius")
    return spec


def _read_joint(fields: Fields, a: int, b: int, path: str) -> JointSpec:
    fixed = fields.boolean("is_fixed_joint", False)
    spec = JointSpec(
        path=path,
        a=a,
        b=b,
        anchor_a=fields.vector("a_relative_pos"),
        anchor_b=fields.vector("b_relative_pos"),
        ref_angle=fields.number("rotation", 0.0),
        fixed=fixed,
    )
    if not fixed:  # a weld has no motor or limits; their values are left over from editing
        spec.motor_on = fields.boolean("motor_on", False)
        spec.motor_speed = fields.number("motor_speed", 1.0)
        spec.motor_power = fields.number("motor_power", 1.0)
        spec.motor_binding = fields.integer("motor_binding", 0, low=0, high=NUM_MOTOR_BINDINGS - 1)
        if fields.boolean("motor_has_joint_limits", False):
            lo, hi = fields.number("min_rotation"), fields.number("max_rotation")
            if lo > hi:
                raise LevelError(f"{fields.path}: min_rotation {lo} is above max_rotation {hi}")
            spec.limits = (lo, hi)
    return spec


# ---------------------------------------------------------------- export


def _exact(x) -> float:
    """A float32 value as the float64 with the same value (how their files write numbers)."""
    return float(np.float32(x))


def _vec(v) -> dict:
    return {"0": _exact(v[0]), "1": _exact(v[1])}


def _keyed(items: list) -> dict:
    return {str(i): item for i, item in enumerate(items)}


def _rotate(angle: float, v) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def _body_entry(body: BodySpec | None, inv_mass: float, inv_inertia: float, slots: int) -> dict:
    """One polygon or circle slot with `slots` vertex slots (the file's max_polygon_vertices)."""
    if body is None:  # padding slot
        zero = {"0": 0.0, "1": 0.0}
        return dict(position=zero, rotation=0.0, velocity=zero, angular_velocity=0.0, inverse_mass=0.0,
                    inverse_inertia=0.0, friction=1.0, restitution=0.0, collision_mode=1, active=False,
                    n_vertices=0, vertices=_keyed([zero] * slots), radius=0.0, role=0,
                    density=1.0, highlighted=False)
    if body.shape == "polygon":
        clockwise = list(body.vertices)[::-1]
        padded = clockwise + [clockwise[-1]] * (slots - len(clockwise))
        n_vertices, vertices, radius = len(clockwise), [_vec(v) for v in padded], 0.0
    else:
        n_vertices, vertices, radius = 0, [{"0": 0.0, "1": 0.0}] * slots, _exact(body.radius)
    return dict(
        position=_vec(body.position),
        rotation=_exact(body.angle),
        velocity=_vec(body.velocity),
        angular_velocity=_exact(body.angular_velocity),
        inverse_mass=_exact(inv_mass),
        inverse_inertia=_exact(inv_inertia),
        friction=_exact(body.friction),
        restitution=_exact(body.restitution),
        collision_mode=body.collision_mode,
        active=True,
        n_vertices=n_vertices,
        vertices=_keyed(vertices),
        radius=radius,
        role=body.role,
        density=_exact(body.density),
        highlighted=False,
    )


def _manifold() -> dict:
    zero = {"0": 0.0, "1": 0.0}
    return dict(normal=zero, penetration=0.0, collision_point=zero, active=False, acc_impulse_normal=0.0,
                acc_impulse_tangent=0.0, restitution_velocity_target=0.0)


def collision_matrix(num_bodies: int, pairs: list[tuple[int, int]]) -> np.ndarray:
    """(N, N) bool: False for a body with itself and for bodies linked through any chain of joints."""
    linked = np.eye(num_bodies, dtype=bool)
    for a, b in pairs:
        linked[a, b] = linked[b, a] = True
    for _ in range(max(1, math.ceil(math.log2(max(num_bodies, 2))))):
        linked = (linked.astype(np.int32) @ linked.astype(np.int32)) > 0
    return ~linked


def export_errors(spec: LevelSpec) -> list[str]:
    """Why this level cannot be written as a public Kinetix file, whatever the size (empty if it can)."""
    walls = [b for b in spec.bodies if b.shape == "polygon"][:NUM_WALLS]
    if len(walls) < NUM_WALLS or not all(b.fixed for b in walls):
        return [f"Kinetix keeps {NUM_WALLS} fixed polygons (its walls) in polygon slots 0-3, but this "
                f"level's first polygons are {['fixed' if b.fixed else 'dynamic' for b in walls]}; "
                "build levels on kinetix.level.empty_level / add_walls"]
    return []


def _counts(spec: LevelSpec) -> dict[str, int]:
    polygons = sum(b.shape == "polygon" for b in spec.bodies)
    return dict(polygons=polygons, circles=len(spec.bodies) - polygons, joints=len(spec.joints),
                thrusters=len(spec.thrusters))


def _is_public(size: SizeClass) -> bool:
    return size.name in PUBLIC_SIZES and size == SIZES[size.name]


def _choose_size(spec: LevelSpec, own: SizeClass, requested: SizeClass | None, what: str) -> tuple[SizeClass, str]:
    """(size class to write, why in words). A requested size must hold the (split) level. Otherwise: the level's
    own public size (s, m, l) or the next public one that holds it; past l, or for xl and custom levels, the
    level's own capacities grown to hold it (the public loader takes any capacities: env_size custom)."""
    if requested is not None:
        if errors := fit_errors(spec, requested):
            raise LevelError(f"cannot export to the Kinetix format in size {requested.name}{what}: "
                             + "; ".join(errors))
        return requested, ""
    base = own
    if _is_public(own):
        for name in PUBLIC_SIZES[PUBLIC_SIZES.index(own.name):]:
            if not fit_errors(spec, SIZES[name]):
                return SIZES[name], "" if name == own.name else _too_small(spec, own)
        base = SIZES[PUBLIC_SIZES[-1]]
    elif not fit_errors(spec, own):
        return own, ""
    counts = _counts(spec)
    bodies = counts["polygons"] + counts["circles"]
    over = ([f"{bodies} bodies ({counts['polygons']} polygons, {counts['circles']} circles) > {MAX_BODIES}"]
            if bodies > MAX_BODIES else [])
    over += [f"{counts[kind]} {kind} > {limit}" for kind, limit in (("joints", MAX_JOINTS),
                                                                   ("thrusters", MAX_THRUSTERS))
             if counts[kind] > limit]
    if over:
        raise LevelError(f"cannot export to the Kinetix format{what}: the level needs " + "; ".join(over)
                         + " allowed in any size class")
    grown = {kind: max(getattr(base, kind), n) for kind, n in counts.items()}
    size = next((s for s in SIZES.values() if s.counts() == grown), None) or SizeClass("custom", **grown)
    return size, _too_small(spec, base)


def _too_small(spec: LevelSpec, size: SizeClass) -> str:
    return f"size {size.name} is too small for it: " + "; ".join(fit_errors(spec, size))


@dataclasses.dataclass
class Export:
    """A level as written to a public Kinetix file: polygons of 5-8 vertices split, in the size class chosen."""

    file: LevelFile  # the level written (built from split.spec in `size`)
    split: Split
    size_reason: str  # why the size is bigger than the level's, in words ("" if it is not)

    @property
    def size(self) -> SizeClass:
        return self.file.size

    def document(self) -> dict:
        return document(self.file)

    def text(self) -> str:
        """The file's text (strict JSON: no NaN or infinity)."""
        return json.dumps(self.document(), allow_nan=False) + "\n"

    def summary(self) -> str:
        """What export did, in words: "split 2 polygons (8 and 6 vertices) into 5 parts welded by 3 fixed joints;
        exported as size l"."""
        size, split = self.size, self.split.summary()
        if _is_public(size):
            where = f"exported as size {size.name}" + (f" ({self.size_reason})" if self.size_reason else "")
        else:
            where = (f"exported as size {size.name} ({size.polygons} polygons, {size.circles} circles, {size.joints} "
                     f"joints, {size.thrusters} thrusters)" + (f"; {self.size_reason}" if self.size_reason else "")
                     + f"; the public Kinetix, whose own sizes are {', '.join(PUBLIC_SIZES)}, loads it as a custom "
                     "size (env_size custom)")
        return f"{split}; {where}" if split else where

    def notes(self) -> list[str]:
        """What the public Kinetix does differently with the file, in sentences for a person (empty if nothing)."""
        spec, notes = self.split.spec, []
        auto = sum(j.motor_auto for j in spec.joints)
        if auto:
            notes.append(f"{auto} \"always driven\" motor{'s' if auto > 1 else ''} lose{'s' if auto == 1 else ''} "
                         "that setting: the public format has no field for it, so there the motor runs only from its "
                         "keys.")
        driven = {k: f for k, f in self.split.motor_scale.items() if spec.joints[k].motor_on}
        if driven:
            listed = ", ".join(f"{spec.joints[k].path} x{factor:.3g}" for k, factor in driven.items())
            one = len(driven) == 1
            drives = "this motor now drives" if one else "these motors now drive"
            notes.append(f"Motor power scaled ({listed}): {drives} one part of a split polygon, and a motor's "
                         "torque limit grows with the inertia of the bodies it joins, so the power is raised to keep "
                         "the limit it had on the whole polygon.")
        scored = [p for p in self.split.polygons if ROLE_NAMES[spec.bodies[p.body].role] in ("green", "blue")]
        if scored:
            listed = ", ".join(f"{p.path} ({ROLE_NAMES[spec.bodies[p.body].role]}, {len(p.parts)} parts)"
                               for p in scored)
            one = len(scored) == 1
            notes.append(f"The dense reward there sums the distances of every green-blue pair of bodies, so the "
                         f"split polygon{'' if one else 's'} {listed} count{'s' if one else ''} once per part: the "
                         "shaping reward changes scale, the win and loss rewards do not.")
        return notes


def prepare(file: LevelFile, size: str | SizeClass | None = None) -> Export:
    """The level as it will be written (see `Export`); `size` forces a size class, which must hold it."""
    spec = describe(file.level, file.params, file.name)
    if errors := export_errors(spec):
        raise LevelError("cannot export to the Kinetix format: " + "; ".join(errors))
    split = split_polygons(spec)
    what = f" after it {split.summary()}" if split.polygons else ""
    chosen, reason = _choose_size(split.spec, file.size, None if size is None else size_class(size), what)
    try:
        built = build(split.spec, chosen)
    except LevelError as error:
        raise LevelError(f"cannot export to the Kinetix format{what}: {error}") from None
    return Export(built, split, reason)


def export_notes(file: LevelFile, size: str | SizeClass | None = None) -> list[str]:
    """What export does and what the public Kinetix does differently, in sentences: the summary first."""
    export = prepare(file, size)
    return [export.summary()] + export.notes()


def write(file: LevelFile, size: str | SizeClass | None = None) -> dict:
    """The level as a JSON-ready dict in the public Kinetix shape (see `prepare` for the splitting and the size)."""
    return document(prepare(file, size).file)


def document(file: LevelFile) -> dict:
    """A level whose polygons have at most 4 vertices as a JSON-ready dict in the public Kinetix shape, padded to
    its size class."""
    level, size, p = file.level, file.size, file.params
    spec = describe(level, p, file.name)
    if too_many := [b.path for b in spec.bodies if b.shape == "polygon" and len(b.vertices) > KINETIX_MAX_VERTICES]:
        raise LevelError(f"{', '.join(too_many)}: more than {KINETIX_MAX_VERTICES} vertices (use write, which "
                         "splits them)")
    P, C = size.polygons, size.circles
    slots = KINETIX_MAX_VERTICES

    sim = level.sim
    active = np.nonzero(np.asarray(sim.bodies.active))[0]
    inv_mass = np.asarray(sim.bodies.inv_mass)[active]
    inv_inertia = np.asarray(sim.bodies.inv_inertia)[active].astype(np.float64)
    polygon_entries, circle_entries, global_index = [], [], []
    for k, body in enumerate(spec.bodies):
        if body.shape == "polygon":
            global_index.append(len(polygon_entries))
            polygon_entries.append(_body_entry(body, inv_mass[k], inv_inertia[k], slots))
        else:
            global_index.append(P + len(circle_entries))
            # Their disc inertia is m r^2 / 4 (ours the textbook m r^2 / 2): write theirs, so the level
            # behaves in their engine like a circle made there.
            their_inv_inertia = 0.0 if body.fixed else 4.0 / (math.pi * body.radius**4 * body.density)
            circle_entries.append(_body_entry(body, inv_mass[k], their_inv_inertia, slots))
    polygon_entries += [_body_entry(None, 0, 0, slots) for _ in range(P - len(polygon_entries))]
    circle_entries += [_body_entry(None, 0, 0, slots) for _ in range(C - len(circle_entries))]

    def world_point(body_index: int, anchor) -> np.ndarray:
        body = spec.bodies[body_index]
        return np.asarray(body.position) + _rotate(body.angle, anchor)

    zero = {"0": 0.0, "1": 0.0}
    joint_entries = []
    for joint in spec.joints:
        limits = joint.limits or (0.0, 0.0)
        joint_entries.append(dict(
            a_index=global_index[joint.a], b_index=global_index[joint.b],
            a_relative_pos=_vec(joint.anchor_a), b_relative_pos=_vec(joint.anchor_b),
            global_position=_vec(world_point(joint.a, joint.anchor_a)), active=True, acc_impulse=zero,
            acc_r_impulse=0.0, motor_speed=_exact(joint.motor_speed), motor_power=_exact(joint.motor_power),
            motor_on=joint.motor_on, motor_has_joint_limits=joint.limits is not None,
            min_rotation=_exact(limits[0]), max_rotation=_exact(limits[1]), is_fixed_joint=joint.fixed,
            rotation=_exact(joint.ref_angle), motor_binding=joint.motor_binding,
        ))
    joint_entries += [dict(
        a_index=0, b_index=0, a_relative_pos=zero, b_relative_pos=zero, global_position=zero, active=False,
        acc_impulse=zero, acc_r_impulse=0.0, motor_speed=0.0, motor_power=0.0, motor_on=False,
        motor_has_joint_limits=False, min_rotation=0.0, max_rotation=0.0, is_fixed_joint=False, rotation=0.0,
        motor_binding=0) for _ in range(size.joints - len(joint_entries))]

    thruster_entries = [dict(
        object_index=global_index[t.body], relative_position=_vec(t.anchor), rotation=_exact(t.angle),
        power=_exact(t.power), global_position=_vec(world_point(t.body, t.anchor)), active=True,
        thruster_binding=t.binding) for t in spec.thrusters]
    thruster_entries += [dict(
        object_index=0, relative_position=zero, rotation=0.0, power=0.0, global_position=zero, active=False,
        thruster_binding=0) for _ in range(size.thrusters - len(thruster_entries))]

    N = P + C
    matrix = collision_matrix(N, [(global_index[j.a], global_index[j.b]) for j in spec.joints])
    num_rr = P * (P - 1) // 2 - NUM_WALLS * (NUM_WALLS - 1) // 2  # pairs of two walls are never checked
    env_state = dict(
        polygon=polygon_entries,
        circle=circle_entries,
        joint=joint_entries,
        thruster=thruster_entries,
        collision_matrix=_keyed([_keyed([bool(x) for x in row]) for row in matrix]),
        acc_rr_manifolds=[_manifold() for _ in range(2 * num_rr)],
        acc_cr_manifolds=[_manifold() for _ in range(P * C)],
        acc_cc_manifolds=[_manifold() for _ in range(C * (C - 1) // 2)],
        gravity=_vec(spec.gravity),
    )
    env_params = dict(
        dt=p.dt, **_THEIR_SOLVER_PARAMS,
        base_motor_speed=p.base_motor_speed, base_motor_power=p.base_motor_power,
        base_thruster_power=p.base_thruster_power, **_THEIR_MOTOR_PARAMS,
        max_timesteps=p.max_timesteps, pixels_per_unit=100, dense_reward_scale=p.dense_reward_scale,
        num_shape_roles=len(ROLE_NAMES),
    )
    static_env_params = dict(
        num_polygons=P, num_circles=C, num_joints=size.joints, num_thrusters=size.thrusters,
        max_polygon_vertices=slots, num_solver_iterations=10, solver_batch_size=16,
        do_warm_starting=True, num_static_fixated_polys=NUM_WALLS, screen_dim={"0": 500, "1": 500}, downscale=4,
        frame_skip=p.frame_skip, max_shape_size=2, num_motor_bindings=NUM_MOTOR_BINDINGS,
        num_thruster_bindings=NUM_THRUSTER_BINDINGS,
    )
    return dict(env_state=env_state, env_params=env_params, static_env_params=static_env_params)
