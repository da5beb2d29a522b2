"""External forces of a substep: gravity and thrusters (step.py's "integrate velocities")."""

from __future__ import annotations

import jax.numpy as jnp

from jax2d.math2d import Pose, Vel, one_hot_rows, pick_rows, rotate
from jax2d.state import SimParams, Thrusters


def thruster_forces(t: Thrusters, actions, M: int, params: SimParams) -> tuple:
    """Per-thruster selection rows (T, M, *batch) and force magnitudes; directions follow the body each substep."""
    sel = one_hot_rows(t.body, M) * t.active.astype(jnp.float32)[:, None]
    magnitude = t.power * params.base_thruster_power * jnp.clip(actions, 0.0, 1.0)
    return sel, magnitude, t


def integrate_velocities(vel: Vel, pose: Pose, dyn, inv_mass, inv_inertia, gravity, forces, h) -> Vel:
    """Velocities after a substep h of gravity (moving bodies) and the thrusters (`forces`: thruster_forces)."""
    sel, magnitude, t = forces
    body_angle = pick_rows(sel, pose.a)
    fx, fy = rotate(jnp.cos(body_angle + t.angle), jnp.sin(body_angle + t.angle), magnitude, 0.0)
    rx, ry = rotate(jnp.cos(body_angle), jnp.sin(body_angle), t.anchor[:, 0], t.anchor[:, 1])
    # Sum thruster by thruster, in slot order: a reduction could add them in another
    # order under vmap and break bitwise batch equality.
    force_x, force_y, torque = jnp.zeros_like(vel.x), jnp.zeros_like(vel.x), jnp.zeros_like(vel.x)
    for t_i in range(sel.shape[0]):
        force_x = force_x + fx[t_i] * sel[t_i]
        force_y = force_y + fy[t_i] * sel[t_i]
        torque = torque + (rx[t_i] * fy[t_i] - ry[t_i] * fx[t_i]) * sel[t_i]
    return Vel(
        vel.x + h * (dyn * gravity[0] + inv_mass * force_x),
        vel.y + h * (dyn * gravity[1] + inv_mass * force_y),
        vel.w + h * inv_inertia * torque,
    )


