"""kinetix's space descriptions (kinetix.actions: Box, Discrete, MultiDiscrete, DictSpace) as Gymnasium spaces, and
the check of an action against them before it goes to the device.

    flat, pixels       Box float32 (flat: [-10, 10] per feature; pixels: (R, R, 3) in [0, 1])
    entity             Dict of Boxes: float32 features, bool masks (polygon_mask, ..., attention_mask), int32 indexes
    multi_discrete     MultiDiscrete([3, 3, 3, 3, 2, 2]) int32
    discrete           Discrete(11)
    continuous         Box float32 (6,): motors in [-1, 1], thrusters in [0, 1]
"""

from __future__ import annotations

import gymnasium
import numpy as np

from kinetix import actions as kinetix_actions


def to_gymnasium(space) -> gymnasium.Space:
    """The Gymnasium space of a kinetix space description."""
    if isinstance(space, kinetix_actions.DictSpace):
        return gymnasium.spaces.Dict({name: to_gymnasium(sub) for name, sub in space.spaces.items()})
    if isinstance(space, kinetix_actions.Discrete):
        if space.shape != ():
            raise TypeError(f"a Discrete of shape {space.shape} has no Gymnasium equivalent")
        return gymnasium.spaces.Discrete(space.n)
    if isinstance(space, kinetix_actions.MultiDiscrete):
        return gymnasium.spaces.MultiDiscrete(np.asarray(space.nvec), dtype=np.int32)
    if isinstance(space, kinetix_actions.Box):
        dtype = np.dtype(space.dtype)
        if dtype == np.dtype(bool):
            return gymnasium.spaces.Box(0, 1, space.shape, np.bool_)
        low = np.broadcast_to(np.asarray(space.low, dtype), space.shape)
        high = np.broadcast_to(np.asarray(space.high, dtype), space.shape)
        return gymnasium.spaces.Box(low, high, space.shape, dtype)
    raise TypeError(f"unknown space description {space!r}")


def check_actions(actions, action_type: str, batch: tuple[int, ...]) -> np.ndarray:
    """`actions` as the array the device takes (int32, or float32 for continuous), with a clear ValueError for the
    wrong shape or type, or a discrete value out of range. batch: () for one environment, (N,) for N."""
    space = kinetix_actions.action_space(action_type)
    array = np.asarray(actions)
    shape = batch + tuple(space.shape)
    if array.shape != shape:
        raise ValueError(f"{action_type} actions must have shape {shape}, got {array.shape}")
    if action_type == "continuous":
        if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
            raise ValueError(f"continuous actions must be numbers, got dtype {array.dtype}")
        return array.astype(np.float32, copy=False)
    if not np.issubdtype(array.dtype, np.integer):
        # Whole floats are accepted (some libraries hand discrete actions back as floats); fractions are not.
        if not np.issubdtype(array.dtype, np.floating) or not np.all(np.isfinite(array) & (array == np.round(array))):
            raise ValueError(f"{action_type} actions must be integers, got {array.dtype} values")
    high = (np.asarray(space.nvec) if action_type == "multi_discrete" else space.n)
    if np.any(array < 0) or np.any(array >= high):
        raise ValueError(f"{action_type} actions out of range: each entry must be in [0, {high}) "
                         f"({'per binding' if action_type == 'multi_discrete' else 'one of the 11 actions'})")
    return array.astype(np.int32, copy=False)
