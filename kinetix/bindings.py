"""From the agent's binding values to per-joint and per-thruster actions.

Joints and thrusters do not get their own actions: each listens to a binding (as in the public
Kinetix), so one policy output drives every joint bound to it. Pure jnp: jit and vmap freely.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from kinetix.level import Level


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
