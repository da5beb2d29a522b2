"""Which bodies touch: read from the contact points the last step found.

A pair touches when one of its contact points has a separation of at most
`tolerance`. Contact points exist up to the speculative distance (4 cm by
default), so the tolerance keeps near misses from counting as touches.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jax2d.pairs import contact_layout
from jax2d.state import SimState

TOUCH_TOLERANCE = 0.01  # m


def touching_slots(state: SimState, tolerance: float = TOUCH_TOLERANCE) -> jax.Array:
    """(S,) bool: the slot's two bodies touched in the last step."""
    c = state.contacts
    return jnp.any(c.active & (c.separation <= tolerance), axis=-1)


def slot_bodies(state: SimState) -> tuple[np.ndarray, np.ndarray]:
    """Constant (S,) arrays of each slot's two global body indices (index N marks padding)."""
    layout = contact_layout(state.num_polygons, state.num_circles)
    return layout.slot_a, layout.slot_b


def touching_matrix(state: SimState, tolerance: float = TOUCH_TOLERANCE) -> jax.Array:
    """(N, N) bool, symmetric: bodies i and j touched in the last step."""
    layout = contact_layout(state.num_polygons, state.num_circles)
    N = state.num_bodies
    eye = np.eye(layout.num_padded, dtype=np.float32)[:, :N]
    sel_a, sel_b = jnp.asarray(eye[layout.slot_a]), jnp.asarray(eye[layout.slot_b])  # (S, N) constants
    t = touching_slots(state, tolerance).astype(jnp.float32)
    m = (sel_a * t[:, None]).T @ sel_b
    return (m + m.T) > 0
