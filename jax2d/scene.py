"""Building and editing scenes: a functional API on SimState, used outside jit.

Every function returns a new state and leaves its input untouched; array shapes
and dtypes never change. Additions take the first inactive slot of their kind
and raise CapacityError when there is none. Positions, anchors and angles are
in the world frame unless a docstring says otherwise.
"""

from __future__ import annotations

import dataclasses
import operator

import jax.numpy as jnp
import numpy as np

from jax2d.geometry import (
    check_positive,
    circle_mass_properties,
    polygon_mass_properties,
    rectangle_vertices,
    validate_polygon,
)
from jax2d.pairs import contact_layout
from jax2d.state import COLLIDE_ALL, COLLIDE_NORMAL, COLLIDE_ONLY_ALL, SimState


class CapacityError(ValueError):
    """The scene has no free slot (or too few vertex slots) for an addition."""


# ---------------------------------------------------------------- small helpers


def _replace_rows(struct, index, **values):
    """A copy of a dataclass of arrays with `field[index] = value` for each given field.

    `index` may be an int or a boolean mask; dtypes and shapes are kept.
    """
    changes = {}
    for name, value in values.items():
        old = getattr(struct, name)
        new = np.array(old)
        new[index] = value
        changes[name] = jnp.asarray(new, dtype=old.dtype)
    return dataclasses.replace(struct, **changes)


def _rotation(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s], [s, c]])


def _vector(value, name: str) -> np.ndarray:
    try:
        v = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be two numbers, got {value!r}") from None
    if v.shape != (2,):
        raise ValueError(f"{name} must be two numbers (x, y), got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be finite, got {v.tolist()}")
    return v


def _scalar(value, name: str, low: float | None = None, high: float | None = None) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(x):
        raise ValueError(f"{name} must be finite, got {x}")
    if (low is not None and x < low) or (high is not None and x > high):
        raise ValueError(f"{name} must be in [{low}, {high}], got {x}")
    return x


def _integer(value, name: str) -> int:
    if isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    try:
        return operator.index(value)
    except TypeError:
        raise ValueError(f"{name} must be an integer, got {value!r}") from None


def _check_unbatched(state: SimState) -> None:
    if state.bodies.active.ndim != 1:
        raise ValueError(f"scene editing works on one scene, got a batch of shape {state.bodies.active.shape[:-1]}")


def _first_free(active, kind: str) -> int:
    free = np.nonzero(~np.asarray(active))[0]
    if len(free) == 0:
        total = len(active)
        if total == 0:
            raise CapacityError(f"no {kind} slot: this scene's capacity has 0 {kind} slots")
        raise CapacityError(f"no free {kind} slot: all {total} {kind} slots are in use")
    return int(free[0])


def _check_body(state: SimState, index, name: str = "body") -> int:
    i = _integer(index, name)
    if not 0 <= i < state.num_bodies:
        raise ValueError(f"{name} index {i} is out of range: the scene has body slots 0..{state.num_bodies - 1}")
    if not bool(state.bodies.active[i]):
        raise ValueError(f"{name} {i} is not an active body")
    return i


def _check_slot(active, index, kind: str) -> int:
    i = _integer(index, f"{kind} index")
    if not 0 <= i < len(active):
        raise ValueError(f"{kind} index {i} is out of range: the scene has {len(active)} {kind} slots")
    if not bool(active[i]):
        raise ValueError(f"{kind} {i} is not active")
    return i


def _is_static(state: SimState, i: int) -> bool:
    return float(state.bodies.inv_mass[i]) == 0.0


def _clear_contacts(state: SimState, body: int) -> SimState:
    """Forget warm-start data of every contact slot involving `body`, so a new body never inherits it."""
    layout = contact_layout(state.num_polygons, state.num_circles)
    rows = (layout.slot_a == body) | (layout.slot_b == body)
    contacts = _replace_rows(
        state.contacts, rows, normal_impulse=0.0, tangent_impulse=0.0, key=-1, active=False, separation=0.0
    )
    return dataclasses.replace(state, contacts=contacts)


def _body_row(position, angle, density, friction, restitution, collision_mode, fixed, velocity, angular_velocity):
    """The validated shape-independent fields of a new body, except its inverse mass and inertia."""
    mode = _integer(collision_mode, "collision_mode")
    if mode not in (COLLIDE_ONLY_ALL, COLLIDE_NORMAL, COLLIDE_ALL):
        raise ValueError(f"collision_mode must be {COLLIDE_ONLY_ALL}, {COLLIDE_NORMAL} or {COLLIDE_ALL}, got {mode}")
    row = dict(
        position=_vector(position, "position"),
        angle=_scalar(angle, "angle"),
        velocity=_vector(velocity, "velocity"),
        angular_velocity=_scalar(angular_velocity, "angular_velocity"),
        density=check_positive(density, "density"),
        friction=_scalar(friction, "friction", low=0.0),
        restitution=_scalar(restitution, "restitution", low=0.0, high=1.0),
        collision_mode=mode,
        active=True,
    )
    if fixed and (np.any(row["velocity"] != 0) or row["angular_velocity"] != 0):
        raise ValueError("a fixed (static) body never moves, so it cannot be given a velocity")
    return row


def _inverse(mass: float, inertia: float, fixed: bool) -> tuple[float, float]:
    return (0.0, 0.0) if fixed else (1.0 / mass, 1.0 / inertia)


def _place_body(state: SimState, index: int, row: dict, mass: float, inertia: float, fixed: bool) -> SimState:
    """Write body `index` from `row` plus its inverse mass and inertia, and forget its old contacts."""
    inv_mass, inv_inertia = _inverse(mass, inertia, fixed)
    bodies = _replace_rows(state.bodies, index, inv_mass=inv_mass, inv_inertia=inv_inertia, **row)
    return _clear_contacts(dataclasses.replace(state, bodies=bodies), index)


# ---------------------------------------------------------------- bodies


def add_polygon(
    state: SimState,
    position,
    vertices,
    *,
    angle: float = 0.0,
    density: float = 1.0,
    friction: float = 1.0,
    restitution: float = 0.0,
    collision_mode: int = COLLIDE_NORMAL,
    fixed: bool = False,
    velocity=(0.0, 0.0),
    angular_velocity: float = 0.0,
) -> tuple[SimState, int]:
    """Add a convex polygon; `vertices` are counter-clockwise, in the body frame, relative to `position`.

    The stored body position is the centroid (position + R(angle) @ centroid) and
    the stored vertices are shifted to be relative to it.
    """
    _check_unbatched(state)
    verts = validate_polygon(vertices)
    if len(verts) > state.max_vertices:
        raise CapacityError(
            f"polygon has {len(verts)} vertices but this scene's capacity allows at most {state.max_vertices}"
        )
    row = _body_row(position, angle, density, friction, restitution, collision_mode, fixed, velocity, angular_velocity)
    mass, inertia, centroid = polygon_mass_properties(verts, row["density"])
    slot = _first_free(state.bodies.active[: state.num_polygons], "polygon")

    local = verts - centroid
    row["vertices"] = np.concatenate([local, np.repeat(local[-1:], state.max_vertices - len(local), axis=0)])
    row["n_vertices"] = len(local)
    row["position"] = row["position"] + _rotation(row["angle"]) @ centroid
    return _place_body(state, slot, row, mass, inertia, fixed), slot


def add_rectangle(state: SimState, position, width: float, height: float, **kwargs) -> tuple[SimState, int]:
    """Add a width x height rectangle centred at `position`; keyword arguments as for add_polygon."""
    return add_polygon(state, position, rectangle_vertices(width, height), **kwargs)


def add_circle(
    state: SimState,
    position,
    radius: float,
    *,
    angle: float = 0.0,
    density: float = 1.0,
    friction: float = 1.0,
    restitution: float = 0.0,
    collision_mode: int = COLLIDE_NORMAL,
    fixed: bool = False,
    velocity=(0.0, 0.0),
    angular_velocity: float = 0.0,
) -> tuple[SimState, int]:
    """Add a circle centred at `position`; returns its global body index (P + circle slot)."""
    _check_unbatched(state)
    row = _body_row(position, angle, density, friction, restitution, collision_mode, fixed, velocity, angular_velocity)
    mass, inertia, _ = circle_mass_properties(radius, row["density"])
    circle_slot = _first_free(state.bodies.active[state.num_polygons :], "circle")
    index = state.num_polygons + circle_slot
    shaped = dataclasses.replace(state, bodies=_replace_rows(state.bodies, circle_slot, radius=float(radius)))
    return _place_body(shaped, index, row, mass, inertia, fixed), index


def body_mass_properties(state: SimState, index: int) -> tuple[float, float]:
    """(mass, inertia about the centre of mass) of body `index` from its shape and density, static or not."""
    i = _check_body(state, index)
    density = float(state.bodies.density[i])
    if i < state.num_polygons:
        n = int(state.bodies.n_vertices[i])
        mass, inertia, _ = polygon_mass_properties(np.asarray(state.bodies.vertices[i, :n]), density)
    else:
        mass, inertia, _ = circle_mass_properties(float(state.bodies.radius[i - state.num_polygons]), density)
    return mass, inertia


def set_fixed(state: SimState, index: int, fixed: bool) -> SimState:
    """Make body `index` static (inverse mass and inertia 0, at rest) or dynamic (mass from shape and density)."""
    _check_unbatched(state)
    i = _check_body(state, index)
    mass, inertia = body_mass_properties(state, i)
    inv_mass, inv_inertia = _inverse(mass, inertia, bool(fixed))
    rows = dict(inv_mass=inv_mass, inv_inertia=inv_inertia)
    if fixed:
        rows.update(velocity=0.0, angular_velocity=0.0)
    return dataclasses.replace(state, bodies=_replace_rows(state.bodies, i, **rows))


def set_velocity(state: SimState, index: int, velocity, angular_velocity: float | None = None) -> SimState:
    """Set body `index`'s linear velocity, and its angular velocity unless that is None."""
    _check_unbatched(state)
    i = _check_body(state, index)
    rows = dict(velocity=_vector(velocity, "velocity"))
    if angular_velocity is not None:
        rows["angular_velocity"] = _scalar(angular_velocity, "angular_velocity")
    moving = np.any(rows["velocity"] != 0) or rows.get("angular_velocity", 0.0) != 0
    if moving and _is_static(state, i):
        raise ValueError(f"body {i} is fixed (static) and never moves; call set_fixed(state, {i}, False) first")
    return dataclasses.replace(state, bodies=_replace_rows(state.bodies, i, **rows))


def remove_body(state: SimState, index: int) -> SimState:
    """Deactivate body `index` and every joint and thruster attached to it."""
    _check_unbatched(state)
    i = _check_body(state, index)
    bodies = _replace_rows(
        state.bodies, i, active=False, velocity=0.0, angular_velocity=0.0, inv_mass=0.0, inv_inertia=0.0
    )
    joints_hit = (np.asarray(state.joints.a) == i) | (np.asarray(state.joints.b) == i)
    joints = _replace_rows(state.joints, joints_hit, active=False, impulse=0.0)
    thrusters = _replace_rows(state.thrusters, np.asarray(state.thrusters.body) == i, active=False)
    new = dataclasses.replace(state, bodies=bodies, joints=joints, thrusters=thrusters)
    return _clear_contacts(new, i)


# ---------------------------------------------------------------- joints


def _add_joint(state, a, b, anchor, *, fixed, motor_on, motor_speed, motor_power, limits) -> tuple[SimState, int]:
    _check_unbatched(state)
    a = _check_body(state, a, "body a")
    b = _check_body(state, b, "body b")
    if a == b:
        raise ValueError(f"a joint needs two different bodies, got body {a} twice")
    if _is_static(state, a) and _is_static(state, b):
        raise ValueError(f"bodies {a} and {b} are both fixed (static); a joint between them does nothing")
    anchor = _vector(anchor, "anchor")
    motor_speed = _scalar(motor_speed, "motor_speed")
    motor_power = _scalar(motor_power, "motor_power", low=0.0)
    lower = upper = 0.0
    if limits is not None:
        try:
            lower, upper = limits
        except (TypeError, ValueError):
            raise ValueError(f"limits must be None or (lower, upper), got {limits!r}") from None
        lower, upper = _scalar(lower, "lower limit"), _scalar(upper, "upper limit")
        if lower > upper:
            raise ValueError(f"joint lower limit {lower} is above upper limit {upper}")
    slot = _first_free(state.joints.active, "joint")

    pos = np.asarray(state.bodies.position, np.float64)
    ang = np.asarray(state.bodies.angle, np.float64)
    joints = _replace_rows(
        state.joints,
        slot,
        a=a,
        b=b,
        anchor_a=_rotation(-ang[a]) @ (anchor - pos[a]),
        anchor_b=_rotation(-ang[b]) @ (anchor - pos[b]),
        ref_angle=ang[b] - ang[a],
        active=True,
        fixed=fixed,
        motor_on=bool(motor_on),
        motor_speed=motor_speed,
        motor_power=motor_power,
        limit_on=limits is not None,
        lower=lower,
        upper=upper,
        impulse=0.0,
    )
    return dataclasses.replace(state, joints=joints), slot


def add_revolute_joint(
    state: SimState,
    a: int,
    b: int,
    anchor,
    *,
    motor_on: bool = False,
    motor_speed: float = 1.0,
    motor_power: float = 1.0,
    limits: tuple[float, float] | None = None,
) -> tuple[SimState, int]:
    """Pin bodies a and b together at the world point `anchor`; returns the joint slot.

    `limits` bound angle_b - angle_a relative to its value now. Motor speed and power
    are in units of params.base_motor_speed and params.base_motor_power.
    """
    motor = dict(motor_on=motor_on, motor_speed=motor_speed, motor_power=motor_power)
    return _add_joint(state, a, b, anchor, fixed=False, limits=limits, **motor)


def add_fixed_joint(state: SimState, a: int, b: int, anchor) -> tuple[SimState, int]:
    """Weld bodies a and b together at the world point `anchor`; returns the joint slot."""
    return _add_joint(state, a, b, anchor, fixed=True, motor_on=False, motor_speed=0.0, motor_power=0.0, limits=None)


def remove_joint(state: SimState, index: int) -> SimState:
    _check_unbatched(state)
    j = _check_slot(state.joints.active, index, "joint")
    return dataclasses.replace(state, joints=_replace_rows(state.joints, j, active=False, impulse=0.0))


# ---------------------------------------------------------------- thrusters


def add_thruster(
    state: SimState, body: int, anchor, *, angle: float, power: float = 1.0, world: bool = True
) -> tuple[SimState, int]:
    """Attach a thruster to `body`; returns the thruster slot.

    With world=True, `anchor` is a world point and `angle` the world direction of the
    force now; with world=False both are already in the body frame (anchor relative
    to the centre of mass). Power is in units of params.base_thruster_power.
    """
    _check_unbatched(state)
    i = _check_body(state, body)
    anchor = _vector(anchor, "anchor")
    angle = _scalar(angle, "angle")
    power = _scalar(power, "power", low=0.0)
    slot = _first_free(state.thrusters.active, "thruster")
    if world:
        body_angle = float(state.bodies.angle[i])
        anchor = _rotation(-body_angle) @ (anchor - np.asarray(state.bodies.position[i], np.float64))
        angle = float(np.arctan2(np.sin(angle - body_angle), np.cos(angle - body_angle)))
    thrusters = _replace_rows(state.thrusters, slot, body=i, anchor=anchor, angle=angle, power=power, active=True)
    return dataclasses.replace(state, thrusters=thrusters), slot


def remove_thruster(state: SimState, index: int) -> SimState:
    _check_unbatched(state)
    t = _check_slot(state.thrusters.active, index, "thruster")
    return dataclasses.replace(state, thrusters=_replace_rows(state.thrusters, t, active=False))
