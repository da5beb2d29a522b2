"""Our level format: explicit, human-readable JSON (see docs/level-format.md).

Only active entities are written, as plain lists; bodies are referred to by their index in
`bodies`. Unknown fields are errors (a misspelt optional field would otherwise be silently
replaced by its default). Numbers are written as the shortest decimal that reads back to the
same float32, so files stay readable and load -> save -> load is bitwise stable.
"""

from __future__ import annotations

import difflib
import json
import math

import numpy as np

from kinetix.formats import BodySpec, JointSpec, LevelSpec, ThrusterSpec, describe
from kinetix.formats.fields import Fields, check_vector
from kinetix.level import (
    NUM_MOTOR_BINDINGS,
    NUM_THRUSTER_BINDINGS,
    PHYSICS_PARAMS,
    ROLE_NAMES,
    SIZES,
    LevelError,
    LevelFile,
    LevelParams,
    SizeClass,
)

FORMAT_VERSION = 1

TOP_FIELDS = ("format_version", "name", "size", "gravity", "env", "bodies", "joints", "thrusters")
SIZE_FIELDS = ("polygons", "circles", "joints", "thrusters", "max_vertices")
ENV_FIELDS = ("max_timesteps", "frame_skip", "dense_reward_scale", "physics")
BODY_FIELDS = ("shape", "position", "angle", "fixed", "role", "density", "friction", "restitution",
               "collision_mode", "velocity", "angular_velocity")
SHAPE_FIELDS = {"polygon": ("vertices",), "circle": ("radius",)}
JOINT_FIELDS = ("type", "a", "b", "anchor", "anchor_a", "anchor_b", "ref_angle", "motor", "limits")
MOTOR_FIELDS = ("on", "speed", "power", "binding", "auto")
THRUSTER_FIELDS = ("body", "anchor", "angle", "power", "binding")


def _reject_unknown(fields: Fields, allowed) -> None:
    unknown = fields.unknown(set(allowed))
    if not unknown:
        return
    hints = []
    for name in unknown:
        close = difflib.get_close_matches(name, allowed, n=1)
        hints.append(f"{name} (did you mean {close[0]}?)" if close else name)
    where = fields.path or "file"
    raise LevelError(f"{where}: unknown field{'s' * (len(unknown) > 1)} {', '.join(hints)}; "
                     f"allowed: {', '.join(allowed)}")


# ---------------------------------------------------------------- reading


def read(data) -> LevelSpec:
    top = Fields(data, "")
    version = top.get("format_version")
    if isinstance(version, bool) or version != FORMAT_VERSION:
        raise LevelError(f"format_version: this program reads version {FORMAT_VERSION}, got {version!r}")
    _reject_unknown(top, TOP_FIELDS)
    bodies = [_read_body(Fields(item, f"bodies[{k}]")) for k, item in enumerate(top.list("bodies"))]
    joints = [_read_joint(Fields(item, f"joints[{k}]"), bodies) for k, item in enumerate(top.list("joints", []))]
    thrusters = [_read_thruster(Fields(item, f"thrusters[{k}]"), len(bodies))
                 for k, item in enumerate(top.list("thrusters", []))]
    return LevelSpec(
        bodies=bodies,
        joints=joints,
        thrusters=thrusters,
        gravity=top.vector("gravity", [0.0, -9.81]),
        params=_read_env(top),
        size=_read_size(top.get("size", None)),
        name=top.string("name", ""),
    )


def _read_size(value) -> SizeClass | None:
    if value is None:
        return None
    if isinstance(value, str):
        if value not in SIZES:
            raise LevelError(f"size: expected one of {', '.join(SIZES)} or an object of capacities, got {value!r}")
        return SIZES[value]
    fields = Fields(value, "size")
    _reject_unknown(fields, SIZE_FIELDS)
    fields.require("polygons", "circles", "joints", "thrusters")
    counts = {k: fields.integer(k, low=0) for k in SIZE_FIELDS[:4]}
    return SizeClass("custom", **counts, max_vertices=fields.integer("max_vertices", 8, low=3, high=8))


def _read_env(top: Fields) -> LevelParams:
    if "env" not in top.data:
        top.read.add("env")
        return LevelParams()
    env = top.child("env")
    _reject_unknown(env, ENV_FIELDS)
    defaults = LevelParams()
    values = dict(
        max_timesteps=env.integer("max_timesteps", defaults.max_timesteps),
        frame_skip=env.integer("frame_skip", defaults.frame_skip),
        dense_reward_scale=env.number("dense_reward_scale", defaults.dense_reward_scale),
    )
    physics = env.child("physics", {})
    _reject_unknown(physics, PHYSICS_PARAMS)
    values["dt"] = physics.number("dt", defaults.dt)
    for name in PHYSICS_PARAMS[1:]:
        values[name] = physics.number(name, getattr(defaults, name))
    return LevelParams(**values)


def _read_body(fields: Fields) -> BodySpec:
    fields.require("shape", "position")
    shape = fields.string("shape")
    if shape not in SHAPE_FIELDS:
        raise LevelError(f"{fields.where('shape')}: expected polygon or circle, got {shape!r}")
    _reject_unknown(fields, BODY_FIELDS + SHAPE_FIELDS[shape])
    fields.require(*SHAPE_FIELDS[shape])
    role = fields.string("role", "none")
    if role not in ROLE_NAMES:
        raise LevelError(f"{fields.where('role')}: expected one of {', '.join(ROLE_NAMES)}, got {role!r}")
    spec = BodySpec(
        path=fields.path,
        shape=shape,
        position=fields.vector("position"),
        angle=fields.number("angle", 0.0),
        fixed=fields.boolean("fixed", False),
        role=ROLE_NAMES.index(role),
        density=fields.number("density", 1.0),
        friction=fields.number("friction", 1.0),
        restitution=fields.number("restitution", 0.0),
        collision_mode=fields.integer("collision_mode", 1, low=0, high=2),
        velocity=fields.vector("velocity", [0.0, 0.0]),
        angular_velocity=fields.number("angular_velocity", 0.0),
    )
    if shape == "polygon":
        vertices = fields.list("vertices")
        spec.vertices = [check_vector(v, f"{fields.where('vertices')}[{k}]") for k, v in enumerate(vertices)]
    else:
        spec.radius = fields.number("radius")
    return spec


def _rotate(angle: float, v) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def _read_joint(fields: Fields, bodies: list[BodySpec]) -> JointSpec:
    joint_type = fields.string("type", "revolute")
    if joint_type not in ("revolute", "fixed"):
        raise LevelError(f"{fields.where('type')}: expected revolute or fixed, got {joint_type!r}")
    allowed = JOINT_FIELDS if joint_type == "revolute" else tuple(f for f in JOINT_FIELDS if f not in
                                                                 ("motor", "limits"))
    _reject_unknown(fields, allowed)
    fields.require("a", "b")
    n = len(bodies)
    if n == 0:
        raise LevelError(f"{fields.path}: a joint needs bodies, but the level has none")
    a = fields.integer("a", low=0, high=n - 1)
    b = fields.integer("b", low=0, high=n - 1)
    if "anchor" in fields.data:  # one world point, converted to both body frames
        if "anchor_a" in fields.data or "anchor_b" in fields.data:
            raise LevelError(f"{fields.path}: give either anchor (world) or anchor_a and anchor_b, not both")
        world = np.array(fields.vector("anchor"))
        anchor_a = tuple(float(x) for x in _rotate(-bodies[a].angle, world - np.array(bodies[a].position)))
        anchor_b = tuple(float(x) for x in _rotate(-bodies[b].angle, world - np.array(bodies[b].position)))
    else:
        fields.require("anchor_a", "anchor_b")
        anchor_a, anchor_b = fields.vector("anchor_a"), fields.vector("anchor_b")
    spec = JointSpec(path=fields.path, a=a, b=b, anchor_a=anchor_a, anchor_b=anchor_b,
                     ref_angle=fields.number("ref_angle", None) if "ref_angle" in fields.data else None,
                     fixed=joint_type == "fixed")
    if joint_type == "revolute":
        motor_value = fields.get("motor", None)
        if motor_value is not None:
            motor = fields.child("motor")
            _reject_unknown(motor, MOTOR_FIELDS)
            spec.motor_on = motor.boolean("on", True)
            spec.motor_speed = motor.number("speed", 1.0)
            spec.motor_power = motor.number("power", 1.0)
            spec.motor_binding = motor.integer("binding", 0, low=0, high=NUM_MOTOR_BINDINGS - 1)
            spec.motor_auto = motor.boolean("auto", False)
        limits = fields.get("limits", None)
        if limits is not None:
            lo, hi = check_vector(limits, fields.where("limits"))
            if lo > hi:
                raise LevelError(f"{fields.where('limits')}: lower {lo} is above upper {hi}")
            spec.limits = (lo, hi)
    return spec


def _read_thruster(fields: Fields, num_bodies: int) -> ThrusterSpec:
    _reject_unknown(fields, THRUSTER_FIELDS)
    fields.require("body", "anchor")
    if num_bodies == 0:
        raise LevelError(f"{fields.path}: a thruster needs a body, but the level has none")
    return ThrusterSpec(
        path=fields.path,
        body=fields.integer("body", low=0, high=num_bodies - 1),
        anchor=fields.vector("anchor"),
        angle=fields.number("angle", 0.0),
        power=fields.number("power", 1.0),
        binding=fields.integer("binding", 0, low=0, high=NUM_THRUSTER_BINDINGS - 1),
    )


# ---------------------------------------------------------------- writing


def write(file: LevelFile) -> dict:
    """The level as a JSON-ready dict of our format."""
    spec = describe(file.level, file.params, file.name)
    size = file.size
    if size.name in SIZES and SIZES[size.name] == size:
        size_value = size.name
    else:
        size_value = size.counts() | ({} if size.max_vertices == 8 else {"max_vertices": size.max_vertices})
    p = file.params
    return {
        "format_version": FORMAT_VERSION,
        "name": file.name,
        "size": size_value,
        "gravity": list(spec.gravity),
        "env": {
            "max_timesteps": p.max_timesteps,
            "frame_skip": p.frame_skip,
            "dense_reward_scale": p.dense_reward_scale,
            "physics": {name: getattr(p, name) for name in PHYSICS_PARAMS},
        },
        "bodies": [_body_dict(body) for body in spec.bodies],
        "joints": [_joint_dict(joint) for joint in spec.joints],
        "thrusters": [
            {"body": t.body, "anchor": list(t.anchor), "angle": t.angle, "power": t.power, "binding": t.binding}
            for t in spec.thrusters
        ],
    }


def _body_dict(body: BodySpec) -> dict:
    out = {"shape": body.shape, "position": list(body.position), "angle": body.angle}
    if body.shape == "polygon":
        out["vertices"] = [list(v) for v in body.vertices]
    else:
        out["radius"] = body.radius
    out.update(
        fixed=body.fixed,
        role=ROLE_NAMES[body.role],
        density=body.density,
        friction=body.friction,
        restitution=body.restitution,
        collision_mode=body.collision_mode,
        velocity=list(body.velocity),
        angular_velocity=body.angular_velocity,
    )
    return out


def _joint_dict(joint: JointSpec) -> dict:
    out = {
        "type": "fixed" if joint.fixed else "revolute",
        "a": joint.a,
        "b": joint.b,
        "anchor_a": list(joint.anchor_a),
        "anchor_b": list(joint.anchor_b),
        "ref_angle": joint.ref_angle,
    }
    if not joint.fixed:
        out["motor"] = {"on": joint.motor_on, "speed": joint.motor_speed, "power": joint.motor_power,
                        "binding": joint.motor_binding, "auto": joint.motor_auto}
        out["limits"] = list(joint.limits) if joint.limits is not None else None
    return out


def dumps(file: LevelFile, width: int = 100) -> str:
    """Our format as text: indented, with every value that fits on one line kept on one line (easy to diff)."""
    return _format(write(file), 0, width) + "\n"


def _format(value, indent: int, width: int, prefix: int = 0) -> str:
    """`value` at `indent`, its first line already holding `prefix` characters (a key)."""
    flat = json.dumps(value, allow_nan=False)
    if indent + prefix + len(flat) <= width or not isinstance(value, (dict, list)) or not value:
        return flat
    pad = " " * (indent + 2)
    if isinstance(value, dict):
        items = []
        for key, item in value.items():
            head = f"{json.dumps(key)}: "
            items.append(pad + head + _format(item, indent + 2, width, len(head)))
    else:
        items = [pad + _format(item, indent + 2, width) for item in value]
    opening, closing = ("{", "}") if isinstance(value, dict) else ("[", "]")
    return opening + "\n" + ",\n".join(items) + "\n" + " " * indent + closing
