"""The last stage of a step: write the solved bodies and impulses back into the state, clamped and guarded."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from jax2d.math2d import Pose, Vel
from jax2d.state import Contacts, SimParams, SimState


def store(state: SimState, params: SimParams, pose: Pose, vel: Vel, cimp, jimp, manifold, valid, dyn) -> SimState:
    """Write the result back for one scene, clamped; a body whose result is not finite keeps its old pose and stops.

    pose, vel: (M,) padded bodies; cimp: contact_solver.ContactImpulses per slot; jimp: (J, 6) joint impulses;
    manifold, valid: the step's manifolds and which of their points were solved; dyn: (M,) 1 for moving bodies.
    The new state's `frozen` counts the bodies the guard stopped: it keeps NaN out of the scene, so without the
    count a test that looks for NaN could not see that it fired.
    """
    b = state.bodies
    N = b.active.shape[0]
    vx, vy, w = vel.x[:N], vel.y[:N], vel.w[:N]
    speed = jnp.sqrt(vx * vx + vy * vy)
    scale = jnp.where(speed > params.max_linear_speed, params.max_linear_speed / jnp.maximum(speed, 1e-6), 1.0)
    vx, vy = vx * scale, vy * scale
    w = jnp.clip(w, -params.max_angular_speed, params.max_angular_speed)
    x = jnp.clip(pose.x[:N], -params.max_position, params.max_position)
    y = jnp.clip(pose.y[:N], -params.max_position, params.max_position)
    a = pose.a[:N]
    moving = dyn[:N] > 0
    ok = moving & jnp.isfinite(vx) & jnp.isfinite(vy) & jnp.isfinite(w) & jnp.isfinite(x) & jnp.isfinite(y) \
        & jnp.isfinite(a)
    position = jnp.where(ok[:, None], jnp.stack([x, y], axis=1), b.position)
    bodies = dataclasses.replace(
        b,
        position=position,
        angle=jnp.where(ok, a, b.angle),
        velocity=jnp.where(ok[:, None], jnp.stack([vx, vy], axis=1), 0.0),
        angular_velocity=jnp.where(ok, w, 0.0),
    )
    finite = lambda z: jnp.where(jnp.isfinite(z), z, 0.0)  # noqa: E731
    joints = dataclasses.replace(state.joints, impulse=finite(jimp))
    contacts = Contacts(
        normal_impulse=finite(cimp.normal),
        tangent_impulse=finite(cimp.tangent),
        key=jnp.where(valid, manifold.key, -1),
        active=valid,
        separation=jnp.where(valid, finite(manifold.separation), 0.0),
    )
    frozen = jnp.sum(moving & ~ok, dtype=jnp.int32)
    return SimState(bodies, joints, state.thrusters, contacts, state.gravity, frozen)
