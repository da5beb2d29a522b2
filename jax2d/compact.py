"""A pytree packed into one uint32 vector, for jitted calls made one at a time from Python.

JAX pays about 2 µs per argument leaf and per result leaf on every call of a jitted
function. A scene's state has 39 leaves and its params 15, so one `jit(step)` call at
batch 1 spent ~0.22 ms just crossing the boundary, as long as the step itself at s. An
interactive loop (the server, a person playing) keeps its state packed instead:

    state = jax2d.jit(pack)(scene)                       # once
    params = jax2d.jit(pack)(SimParams())
    stepper = jax2d.jit(step_compact, static_argnames="config")
    state = stepper(state, params, motor, thrust)       # 4 leaves in, 1 out
    scene = unpack_host(state)                          # numpy, one device-to-host copy

Packing is exact: 32-bit leaves are bitcast, bools stored as 0 / 1. Inside `jit` the
packing costs one concatenation and the unpacking only slices, which fuse into their users.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

WORD = np.dtype(np.uint32)
_BITCAST = (np.dtype(np.float32), np.dtype(np.int32), np.dtype(np.uint32))


@dataclasses.dataclass(frozen=True)
class Layout:
    """Where each leaf of a pytree lives in the packed vector (static: hashable, part of the jit key)."""

    treedef: Any
    shapes: tuple[tuple[int, ...], ...]
    dtypes: tuple[np.dtype, ...]
    offsets: tuple[int, ...]  # start of each leaf, in words
    size: int  # total words


def layout_of(tree) -> Layout:
    """The layout of a pytree of arrays (or ShapeDtypeStructs). Raises TypeError for a leaf it cannot pack."""
    leaves, treedef = jax.tree.flatten(tree)
    shapes, dtypes, offsets, size = [], [], [], 0
    for i, leaf in enumerate(leaves):
        dtype = np.dtype(leaf.dtype)
        if dtype not in _BITCAST and dtype != np.dtype(bool):
            raise TypeError(f"cannot pack leaf {i} of dtype {dtype}: only float32, int32, uint32 and bool")
        shape = tuple(int(d) for d in np.shape(leaf))
        shapes.append(shape)
        dtypes.append(dtype)
        offsets.append(size)
        size += math.prod(shape)
    return Layout(treedef, tuple(shapes), tuple(dtypes), tuple(offsets), size)


@jax.tree_util.register_pytree_node_class
class Compact:
    """A pytree packed into `buffer` (uint32, (layout.size,)); a pytree of one leaf itself."""

    def __init__(self, buffer, layout: Layout):
        self.buffer = buffer
        self.layout = layout

    def tree_flatten(self):
        return (self.buffer,), self.layout

    @classmethod
    def tree_unflatten(cls, layout, children):
        return cls(children[0], layout)

    def __repr__(self) -> str:
        return f"Compact({self.layout.size} words, {len(self.layout.shapes)} leaves)"


def pack(tree) -> Compact:
    """Pack a pytree of float32 / int32 / uint32 / bool arrays (traceable; jit it when called from Python)."""
    layout = layout_of(tree)
    words = [_to_words(jnp.asarray(x)).reshape(-1) for x in jax.tree.leaves(tree)]
    buffer = jnp.concatenate(words) if words else jnp.zeros((0,), WORD)
    return Compact(buffer, layout)


def update(compact: Compact, old_tree, new_tree) -> Compact:
    """`pack(new_tree)`, writing only the leaves that changed (traceable).

    `old_tree` must be `unpack(compact)` (the very arrays) and `new_tree` a pytree of the same
    layout computed from it: a leaf that is the same object as in `old_tree` passed through
    unchanged and is not written again. A step changes few leaves (poses, velocities,
    impulses), so this is a few in-place slice writes instead of a copy of every leaf.
    """
    layout = layout_of(new_tree)
    if layout != compact.layout:
        raise ValueError("new_tree does not have the layout of the packed tree")
    buffer = compact.buffer
    old_leaves = jax.tree.leaves(old_tree)
    for old, new, start in zip(old_leaves, jax.tree.leaves(new_tree), layout.offsets, strict=True):
        if new is not old:
            buffer = jax.lax.dynamic_update_slice(buffer, _to_words(jnp.asarray(new)).reshape(-1), (start,))
    return Compact(buffer, layout)


def unpack(compact: Compact):
    """The pytree back, as JAX arrays (traceable)."""
    buffer = compact.buffer
    return _rebuild(compact.layout, lambda start, stop: buffer[start:stop], _from_words)


def unpack_host(compact: Compact):
    """The pytree back as numpy arrays, with one device-to-host copy (for reading results in Python)."""
    buffer = np.asarray(compact.buffer)
    return _rebuild(compact.layout, lambda start, stop: buffer[start:stop], _from_words_np)


def _rebuild(layout: Layout, take, convert):
    leaves = []
    for shape, dtype, start in zip(layout.shapes, layout.dtypes, layout.offsets, strict=True):
        words = take(start, start + math.prod(shape))
        leaves.append(convert(words, dtype).reshape(shape))
    return jax.tree.unflatten(layout.treedef, leaves)


def _to_words(x: jax.Array) -> jax.Array:
    if x.dtype == jnp.bool_:
        return x.astype(WORD)
    if x.dtype == WORD:
        return x
    return jax.lax.bitcast_convert_type(x, WORD)


def _from_words(words: jax.Array, dtype: np.dtype) -> jax.Array:
    if dtype == np.dtype(bool):
        return words != 0
    if dtype == WORD:
        return words
    return jax.lax.bitcast_convert_type(words, dtype)


def _from_words_np(words: np.ndarray, dtype: np.dtype) -> np.ndarray:
    return words != 0 if dtype == np.dtype(bool) else words.view(dtype)
