"""The property fields of bodies, joints and thrusters as the panel shows them, and applying edits to them.

Angles the user sees are degrees (joint limits, thruster direction in the world frame); the spec keeps
radians. Joint and thruster fields carry a prefix so one `set_properties` call can never be ambiguous.
"""

from __future__ import annotations

import math

from kinetix.formats import LevelSpec
from kinetix.level import NUM_MOTOR_BINDINGS, NUM_THRUSTER_BINDINGS, PHYSICS_PARAMS, ROLE_NAMES
from kinetix.ranges import RANGES

BODY_FIELDS = ("role", "fixed", "density", "friction", "restitution", "collision_mode")
JOINT_FIELDS = ("joint_type", "motor_on", "motor_speed", "motor_power", "motor_binding", "motor_auto", "limits_on",
                "limit_min", "limit_max")
THRUSTER_FIELDS = ("thruster_power", "thruster_direction", "thruster_binding")
ENV_PARAMS = ("max_timesteps", "frame_skip", "dense_reward_scale")  # LevelParams besides the physics ones
COLLISION_MODES = ("only walls", "normal", "everything")  # jax2d COLLIDE_ONLY_ALL, COLLIDE_NORMAL, COLLIDE_ALL


def body_fields(spec: LevelSpec, i: int) -> dict:
    b = spec.bodies[i]
    return dict(index=i, shape=b.shape, role=ROLE_NAMES[b.role], fixed=b.fixed, density=b.density,
                friction=b.friction, restitution=b.restitution, collision_mode=b.collision_mode)


def joint_fields(spec: LevelSpec, k: int) -> dict:
    j = spec.joints[k]
    low, high = j.limits if j.limits is not None else (-math.pi / 4, math.pi / 4)
    return dict(index=k, a=j.a, b=j.b, joint_type="fixed" if j.fixed else "revolute", motor_on=j.motor_on,
                motor_speed=j.motor_speed, motor_power=j.motor_power, motor_binding=j.motor_binding,
                motor_auto=j.motor_auto, limits_on=j.limits is not None, limit_min=math.degrees(low),
                limit_max=math.degrees(high))


def thruster_fields(spec: LevelSpec, k: int) -> dict:
    t = spec.thrusters[k]
    world = math.degrees(spec.bodies[t.body].angle + t.angle)
    return dict(index=k, body=t.body, thruster_power=t.power, thruster_direction=(world + 180) % 360 - 180,
                thruster_binding=t.binding)


def _number(name, value, low=None, high=None, positive=False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise ValueError(f"{name} must be > 0, got {value:g}")
    if (low is not None and value < low) or (high is not None and value > high):
        raise ValueError(f"{name} must be in [{low}, {high}], got {value:g}")
    return float(value)


def _choice(name, value, count) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < count:
        raise ValueError(f"{name} must be an integer in 0..{count - 1}, got {value!r}")
    return value


def apply(spec: LevelSpec, bodies: list[int], joints: list[int], thrusters: list[int], values: dict) -> None:
    """Set `values` on the given items of `spec` (in place); ValueError names a bad field or value."""
    unknown = set(values) - set(BODY_FIELDS + JOINT_FIELDS + THRUSTER_FIELDS)
    if unknown:
        raise ValueError(f"unknown propert{'ies' if len(unknown) > 1 else 'y'} {', '.join(sorted(unknown))}")
    for name in values:
        if name in BODY_FIELDS and not bodies:
            raise ValueError(f"{name} is a body property, and no body is selected")
        if name in JOINT_FIELDS and not joints:
            raise ValueError(f"{name} is a joint property, and no joint is selected")
        if name in THRUSTER_FIELDS and not thrusters:
            raise ValueError(f"{name} is a thruster property, and no thruster is selected")
    for i in bodies:
        b = spec.bodies[i]
        if "role" in values:
            role = values["role"]
            b.role = ROLE_NAMES.index(role) if role in ROLE_NAMES else _choice("role", role, len(ROLE_NAMES))
        if "fixed" in values:
            b.fixed = bool(values["fixed"])
            if b.fixed:
                b.velocity, b.angular_velocity = (0.0, 0.0), 0.0
        if "density" in values:
            b.density = _number("density", values["density"], positive=True)
        if "friction" in values:
            b.friction = _number("friction", values["friction"], low=0.0)
        if "restitution" in values:
            b.restitution = _number("restitution", values["restitution"], low=0.0, high=1.0)
        if "collision_mode" in values:
            mode = values["collision_mode"]
            b.collision_mode = (COLLISION_MODES.index(mode) if mode in COLLISION_MODES
                                else _choice("collision mode", mode, len(COLLISION_MODES)))
    for k in joints:
        j = spec.joints[k]
        if "joint_type" in values:
            if values["joint_type"] not in ("revolute", "fixed"):
                raise ValueError(f"joint type must be revolute or fixed, got {values['joint_type']!r}")
            j.fixed = values["joint_type"] == "fixed"
        if "motor_on" in values:
            j.motor_on = bool(values["motor_on"])
        if "motor_speed" in values:
            j.motor_speed = _number("motor speed", values["motor_speed"])
        if "motor_power" in values:
            j.motor_power = _number("motor power", values["motor_power"], low=0.0)
        if "motor_binding" in values:
            j.motor_binding = _choice("motor binding", values["motor_binding"], NUM_MOTOR_BINDINGS)
        if "motor_auto" in values:
            j.motor_auto = bool(values["motor_auto"])
        low, high = j.limits if j.limits is not None else (-math.pi / 4, math.pi / 4)
        on = bool(values.get("limits_on", j.limits is not None))
        if "limit_min" in values:
            low = math.radians(_number("limit min", values["limit_min"], -360, 360))
        if "limit_max" in values:
            high = math.radians(_number("limit max", values["limit_max"], -360, 360))
        if on and low > high:
            raise ValueError(f"limit min {math.degrees(low):g} deg is above limit max {math.degrees(high):g} deg")
        j.limits = (low, high) if on else None
    for k in thrusters:
        t = spec.thrusters[k]
        if "thruster_power" in values:
            t.power = _number("thruster power", values["thruster_power"], low=0.0)
        if "thruster_direction" in values:
            world = math.radians(_number("thruster direction", values["thruster_direction"]))
            t.angle = world - spec.bodies[t.body].angle
        if "thruster_binding" in values:
            t.binding = _choice("thruster binding", values["thruster_binding"], NUM_THRUSTER_BINDINGS)


# Episode and physics settings (kinetix.level.LevelParams) with the ranges the editor accepts. Frame skip and the
# time step change the compiled play step, so a new value compiles once on the next play (10-15 s cold).
# The bounds are the level format's own (kinetix.ranges), so the editor never accepts what a file may not hold.
PARAM_RANGES: dict[str, tuple[type, float, float]] = {
    name: (int if r.integer else float, r.low, r.high)
    for name, r in ((name, RANGES[f"env.{name}" if name in ENV_PARAMS else f"env.physics.{name}"])
                    for name in ENV_PARAMS + PHYSICS_PARAMS)
}


def checked_params(params, values: dict):
    """`params` (a LevelParams) with `values` set; ValueError names an unknown field or a value out of range."""
    import dataclasses

    changes = {}
    for name, value in values.items():
        if name not in PARAM_RANGES:
            raise ValueError(f"unknown level setting {name!r}; known: {', '.join(PARAM_RANGES)}")
        kind, low, high = PARAM_RANGES[name]
        if kind is int:
            if isinstance(value, float) and value.is_integer():
                value = int(value)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise ValueError(f"{name} must be an integer in [{low}, {high}], got {value!r}")
            changes[name] = value
        else:
            changes[name] = _number(name, value, low, high)
    return dataclasses.replace(params, **changes)
