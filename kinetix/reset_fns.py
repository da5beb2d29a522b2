"""Reset functions: `key -> Level`, what the environment starts each episode from.

All are pure and jit/vmap-able. Levels given to one environment must share its size class (capacity);
`kinetix.levels.resize` fits a level into a larger size.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp

from kinetix.level import Level, LevelError, LevelFile, SizeClass, size_class

ResetFn = Callable[[jax.Array], Level]


def _as_level(level: Level | LevelFile) -> Level:
    return level.level if isinstance(level, LevelFile) else level


def reset_single(level: Level | LevelFile) -> ResetFn:
    """Always the same level."""
    level = _as_level(level)
    if level.sim.bodies.active.ndim != 1:
        raise LevelError("reset_single takes one level; use reset_list for a stack of levels")
    return lambda key: level


def stack_levels(levels: Sequence[Level | LevelFile]) -> Level:
    """One Level whose arrays have a leading axis over `levels` (all of one capacity)."""
    levels = [_as_level(lv) for lv in levels]
    if not levels:
        raise LevelError("no levels to stack")
    capacities = {lv.capacity for lv in levels}
    if len(capacities) > 1:
        raise LevelError(f"levels of different capacities cannot be stacked: {sorted(map(str, capacities))}; "
                         f"use kinetix.levels.resize to bring them to one size")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *levels)


def reset_list(levels: Level | Sequence[Level | LevelFile]) -> ResetFn:
    """A level drawn uniformly from `levels`: a sequence of levels, or one Level stacked along a leading axis."""
    stacked = levels if isinstance(levels, Level) else stack_levels(levels)
    if stacked.sim.bodies.active.ndim != 2:
        raise LevelError("reset_list needs a stack of levels (leading axis), got a single level")
    count = stacked.sim.bodies.active.shape[0]

    def reset(key: jax.Array) -> Level:
        i = list_index(key, count)
        return jax.tree.map(lambda x: x[i], stacked)

    return reset


def list_index(key: jax.Array, count: int) -> jax.Array:
    """Which of `count` stacked levels reset_list's reset draws with `key` (int32 scalar): a caller holding per-level
    data beside the levels (their EnvParams, say) picks the same row."""
    return jax.random.randint(key, (), 0, count)


def reset_random(size: str | SizeClass, generator: Callable[[jax.Array], Level] | None = None,
                 params=None) -> ResetFn:
    """A freshly generated level every episode: `generator(key) -> Level`, by default
    `kinetix.generate.sample_level(key, size, params)` (imported on first use; params None: its defaults).
    Checks the generated level's capacity against `size` once, by shape only."""
    size = size_class(size)
    if generator is None:
        from kinetix.generate import sample_level

        def generator(key: jax.Array) -> Level:
            return sample_level(key, size) if params is None else sample_level(key, size, params)

    level = jax.eval_shape(generator, jax.random.PRNGKey(0))
    if not isinstance(level, Level) or level.capacity != size.capacity:
        got = level.capacity if isinstance(level, Level) else type(level).__name__
        raise LevelError(f"the generator must give levels of size {size.name} ({size.capacity}), got {got}")
    return generator
