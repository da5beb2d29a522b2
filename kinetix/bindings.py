"""From the agent's binding values to per-joint and per-thruster actions.

Joints and thrusters do not get their own actions: each listens to a binding (as in the public
Kinetix), so one policy output drives every joint bound to it. `expand_actions` is pure jnp (jit and vmap
freely); `clockwise_values` reads one level on the host (for the keyboard's mapping, server.play.steps).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from kinetix.level import NUM_MOTOR_BINDINGS, NUM_THRUSTER_BINDINGS, Level


def expand_actions(level: Level, motor_binding_values: jax.Array,
                   thruster_binding_values: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(motor_actions (J,), thruster_actions (T,)) for jax2d.step.

    motor_binding_values: (NUM_MOTOR_BINDINGS,) in [-1, 1]; joint j gets the value of its binding,
    or +1 if it is motor_auto. thruster_binding_values: (NUM_THRUSTER_BINDINGS,) in [0, 1]; thruster t
    gets the value of its binding. Inactive joints and thrusters get 0. Values are not clipped here
    (jax2d.step clips them to their ranges).
    """
    motor_values = jnp.asarray(motor_binding_values, jnp.float32)
    thruster_values = jnp.asarray(thruster_binding_values, jnp.float32)
    joints, thrusters = level.sim.joints, level.sim.thrusters
    motor = jnp.where(level.motor_auto, 1.0, motor_values[level.motor_bindings])
    thrust = thruster_values[level.thruster_bindings]
    return jnp.where(joints.active, motor, 0.0), jnp.where(thrusters.active, thrust, 0.0)


def bound_bindings(level: Level) -> jax.Array:
    """(NUM_MOTOR_BINDINGS + NUM_THRUSTER_BINDINGS,) bool: which bindings the level's actions reach.

    A motor binding counts when an active, motor-on joint that is not motor_auto listens to it (an auto joint
    ignores the action); a thruster binding when an active thruster does. Pure jnp: jit and vmap freely.
    """
    joints, thrusters = level.sim.joints, level.sim.thrusters
    driven = joints.active & joints.motor_on & ~level.motor_auto
    motors = jnp.arange(NUM_MOTOR_BINDINGS)[:, None] == level.motor_bindings[None, :]
    thrust = jnp.arange(NUM_THRUSTER_BINDINGS)[:, None] == level.thruster_bindings[None, :]
    return jnp.concatenate([jnp.any(motors & driven[None, :], -1), jnp.any(thrust & thrusters.active[None, :], -1)])


HUB_TOLERANCE = 1e-3  # metres: anchors this close to their bodies' centres count as equally centred


def _joint_wheel_is_a(static: tuple[bool, bool], circle: tuple[bool, bool], hub: tuple[float, float],
                      inv_mass: tuple[float, float]) -> bool:
    """Whether body a (not b) of a motor joint is its "wheel", the part a player sees turning. Per pair (a, b).

    The rule, in order: the body that moves when the other is fixed; else the circle when the other is a polygon;
    else the body held nearer its own centre (a wheel turns about its hub, the frame holds it off-centre); else the
    heavier body (a ball around a smaller weight); else a.
    """
    if static[0] != static[1]:
        return static[1]
    if circle[0] != circle[1]:
        return circle[0]
    if abs(hub[0] - hub[1]) > HUB_TOLERANCE:
        return hub[0] < hub[1]
    return inv_mass[0] <= inv_mass[1]


def clockwise_values(level: Level) -> np.ndarray:
    """Per motor binding (NUM_MOTOR_BINDINGS,), the binding value (+1 or -1) that turns its wheel clockwise.

    A motor drives d(angle_b - angle_a)/dt towards motor_speed x value (jax2d; angles grow anticlockwise, y up),
    so which sign turns the visible wheel clockwise depends on which of the joint's bodies is the wheel
    (`_joint_wheel_is_a`) and on the sign of its motor speed. The keyboard uses this so that one rule holds on
    every level: the right-hand key of a pair turns the wheel clockwise, so a car rolls right. A binding shared by
    joints that disagree follows the majority (ties: its first joint). Bindings with no keyboard-driven motor
    (none, or only motor_auto joints) get -1. Host numpy, for one (unbatched) level.
    """
    b, j = level.sim.bodies, level.sim.joints
    (inv_mass, n_poly, a_idx, b_idx, anchor_a, anchor_b, active, fixed, motor_on, speed, bindings, auto) = (
        np.asarray(x) for x in jax.device_get((b.inv_mass, b.vertices.shape[0], j.a, j.b, j.anchor_a, j.anchor_b,
                                               j.active, j.fixed, j.motor_on, j.motor_speed, level.motor_bindings,
                                               level.motor_auto)))
    n_poly = int(n_poly)
    votes = np.zeros(NUM_MOTOR_BINDINGS)
    first = np.zeros(NUM_MOTOR_BINDINGS)
    for k in np.flatnonzero(active & ~fixed & motor_on & ~auto & (speed != 0)):
        ia, ib = int(a_idx[k]), int(b_idx[k])
        wheel_a = _joint_wheel_is_a((bool(inv_mass[ia] == 0), bool(inv_mass[ib] == 0)), (ia >= n_poly, ib >= n_poly),
                                    (float(np.hypot(*anchor_a[k])), float(np.hypot(*anchor_b[k]))),
                                    (float(inv_mass[ia]), float(inv_mass[ib])))
        # Wheel a turns at -(speed x value) relative to b, wheel b at +(speed x value): clockwise is negative.
        value = np.sign(speed[k]) * (1.0 if wheel_a else -1.0)
        binding = int(np.clip(bindings[k], 0, NUM_MOTOR_BINDINGS - 1))
        votes[binding] += value
        if first[binding] == 0:
            first[binding] = value
    out = np.where(votes != 0, np.sign(votes), first)
    return np.where(out == 0, -1.0, out).astype(np.int32)
