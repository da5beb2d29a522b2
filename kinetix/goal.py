"""The goal every level shares: green touches blue (win), green touches red (loss).

Read from the contact points of the last physics step (jax2d.touching), so these are
pure functions of a Level and work under jit and vmap.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jax2d.touching import TOUCH_TOLERANCE, slot_bodies, touching_slots
from kinetix.level import ROLE_BLUE, ROLE_GREEN, ROLE_RED, Level

FAR = 100.0  # distance reported when a level has no green or no blue body (m)


def _slot_roles(level: Level):
    a, b = slot_bodies(level.sim)
    roles = jnp.pad(level.roles * level.sim.bodies.active, (0, 1))  # padding slots point at index N
    return roles[np.asarray(a)], roles[np.asarray(b)]


def _pair_touch(level: Level, role_x: int, role_y: int, tolerance: float) -> jax.Array:
    ra, rb = _slot_roles(level)
    pair = ((ra == role_x) & (rb == role_y)) | ((ra == role_y) & (rb == role_x))
    return jnp.any(pair & touching_slots(level.sim, tolerance))


def touch_outcome(level: Level, tolerance: float = TOUCH_TOLERANCE) -> tuple[jax.Array, jax.Array]:
    """(green touches blue, green touches red) from one read of the contacts: what the env checks after every
    physics step (green_touches_blue and green_touches_red each read the contacts and the slots' roles again)."""
    ra, rb = _slot_roles(level)
    touching = touching_slots(level.sim, tolerance)

    def touch(role_y: int) -> jax.Array:
        pair = ((ra == ROLE_GREEN) & (rb == role_y)) | ((ra == role_y) & (rb == ROLE_GREEN))
        return jnp.any(pair & touching)

    return touch(ROLE_BLUE), touch(ROLE_RED)


def green_touches_blue(level: Level, tolerance: float = TOUCH_TOLERANCE) -> jax.Array:
    return _pair_touch(level, ROLE_GREEN, ROLE_BLUE, tolerance)


def green_touches_red(level: Level, tolerance: float = TOUCH_TOLERANCE) -> jax.Array:
    return _pair_touch(level, ROLE_GREEN, ROLE_RED, tolerance)


def goal_distance(level: Level) -> jax.Array:
    """Smallest centre-to-centre distance between an active green and an active blue body (FAR if none)."""
    b = level.sim.bodies
    green = b.active & (level.roles == ROLE_GREEN)
    blue = b.active & (level.roles == ROLE_BLUE)
    d = jnp.linalg.norm(b.position[:, None, :] - b.position[None, :, :] + 1e-12, axis=-1)
    return jnp.min(jnp.where(green[:, None] & blue[None, :], d, FAR))
