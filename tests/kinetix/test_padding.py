"""kinetix.padding: a level grown to a larger size class steps as the original; random-all mixes the classes."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import jax2d
from kinetix.env import EnvConfig, make_env
from kinetix.generate import sample_level
from kinetix.level import SIZES, WALLS_SOLVER
from kinetix.level_source import level_source, mixed_generator
from kinetix.padding import pad_level

S, L = SIZES["s"], SIZES["l"]


def _to_l(index: np.ndarray) -> np.ndarray:
    """Where an s body index lands in l: polygons stay, circles move up by the added polygon slots."""
    return np.where(index < S.polygons, index, index - S.polygons + L.polygons)


@pytest.mark.parametrize("seed", [0, 3, 5])
def test_a_padded_level_steps_as_the_original(seed):
    small = sample_level(jax.random.key(seed), "s")
    big = jax2d.jit(lambda level: pad_level(level, "l"))(small)
    assert big.capacity == L.capacity
    rows = _to_l(np.arange(S.polygons + S.circles))
    # Entities and their references moved together; the added slots are empty.
    np.testing.assert_array_equal(np.asarray(big.sim.bodies.active)[rows], np.asarray(small.sim.bodies.active))
    assert int(big.sim.bodies.active.sum()) == int(small.sim.bodies.active.sum())
    np.testing.assert_array_equal(np.asarray(big.roles)[rows], np.asarray(small.roles))
    np.testing.assert_array_equal(np.asarray(big.sim.joints.a[:S.joints]), _to_l(np.asarray(small.sim.joints.a)))
    np.testing.assert_array_equal(np.asarray(big.sim.thrusters.body[:S.thrusters]),
                                  _to_l(np.asarray(small.sim.thrusters.body)))
    assert int(big.sim.joints.active.sum()) == int(small.sim.joints.active.sum())

    envs = [make_env(EnvConfig(size, solver=WALLS_SOLVER), level) for size, level in (("s", small), ("l", big))]
    states = [env.reset(jax.random.key(0))[1] for env in envs]
    steps = [jax2d.jit(env.step_no_reset) for env in envs]
    key = jax.random.key(100 + seed)
    for _ in range(10):  # random actions: motors and thrusters act through the remapped indices
        key, k = jax.random.split(key)
        action = envs[0].action_space.sample(k)
        states = [step(k, state, action)[1] for step, state in zip(steps, states, strict=True)]
    active = np.asarray(small.sim.bodies.active)
    small_pos = np.asarray(states[0].level.sim.bodies.position)[active]
    big_pos = np.asarray(states[1].level.sim.bodies.position)[rows][active]
    assert np.abs(small_pos - big_pos).max() < 1e-4


def test_padding_only_grows():
    with pytest.raises(ValueError, match="does not fit in size s"):
        pad_level(sample_level(jax.random.key(0), "l"), "s")
    small = sample_level(jax.random.key(0), "s")
    assert pad_level(small, "s") is small


def test_random_all_mixes_the_three_size_classes():
    source = level_source("random-all")
    assert source.random and source.size == L
    # Every leaf keeps the dtype of an l level (a select that promoted the boolean masks to int32 once made
    # ~active a non-mask, and the physics of every level wrong).
    got, want = jax.eval_shape(source.generator, jax.random.key(0)), jax.eval_shape(lambda: sample_level(
        jax.random.key(0), "l"))
    assert [x.dtype for x in jax.tree.leaves(got)] == [x.dtype for x in jax.tree.leaves(want)]
    levels = jax2d.jit(jax.vmap(mixed_generator(("s", "m", "l"))))(jax.random.split(jax.random.key(1), 96))
    assert levels.capacity == L.capacity
    polygons = np.asarray(levels.sim.bodies.active[:, :L.polygons]).sum(axis=1)
    # s levels have at most 5 polygons (walls included), m levels 6; l levels use slots neither has.
    assert (polygons <= S.polygons).sum() >= 10 and (polygons > SIZES["m"].polygons).sum() >= 10, polygons


def test_an_environment_refuses_levels_of_the_wrong_dtypes():
    import jax.numpy as jnp

    from kinetix.level import LevelError

    level = sample_level(jax.random.key(0), "s")
    wrong = jax.tree.map(lambda x: x.astype(jnp.int32) if x.dtype == bool else x, level)
    with pytest.raises(LevelError, match=r"wrong dtypes: \.sim\.bodies\.active is int32, not bool"):
        make_env(EnvConfig("s"), lambda key: wrong)
