"""jax2d.compact: a pytree packed into one buffer, and the packed step for Python loops."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from jax2d import scene
from jax2d.compact import Compact, layout_of, pack, unpack, unpack_host, update
from tests.jax2d.scenes import STEP


def _scene() -> jax2d.SimState:
    state = jax2d.empty_state(jax2d.Capacity(polygons=3, circles=2, joints=1, thrusters=1, max_vertices=4))
    state, floor = scene.add_rectangle(state, (2.5, 0.2), 5.0, 0.4, fixed=True)
    state, box = scene.add_rectangle(state, (2.0, 1.0), 0.6, 0.4, angle=0.3)
    state, wheel = scene.add_circle(state, (2.6, 1.0), 0.2)
    state, _ = scene.add_revolute_joint(state, box, wheel, (2.6, 1.0), motor_on=True, motor_speed=2.0, motor_power=1.0)
    state, _ = scene.add_thruster(state, box, (0.0, 0.0), angle=1.0, power=2.0)
    return state


def _assert_trees_equal(a, b) -> None:
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape
        np.testing.assert_array_equal(x, y)


def test_pack_and_unpack_give_back_every_leaf_bitwise():
    tree = {"f": jnp.array([1.5, -0.0, jnp.inf, jnp.nan], jnp.float32), "i": jnp.array([[-7, 2**31 - 1]], jnp.int32),
            "u": jnp.array([0, 2**32 - 1], jnp.uint32), "b": jnp.array([True, False, True]), "scalar": jnp.float32(3.0),
            "empty": jnp.zeros((0, 2), jnp.float32)}
    packed = jax2d.jit(pack)(tree)
    assert isinstance(packed, Compact) and packed.buffer.shape == (4 + 2 + 2 + 3 + 1,)
    assert len(jax.tree.leaves(packed)) == 1
    back_device, back_host = jax2d.jit(unpack)(packed), unpack_host(packed)
    for back in (back_device, back_host):
        np.testing.assert_array_equal(np.asarray(back["f"]).view(np.uint32), np.asarray(tree["f"]).view(np.uint32))
        for name in ("i", "u", "b", "scalar", "empty"):
            assert np.asarray(back[name]).dtype == np.asarray(tree[name]).dtype
            np.testing.assert_array_equal(np.asarray(back[name]), np.asarray(tree[name]))
    assert isinstance(back_host["f"], np.ndarray)


def test_unpackable_dtype_is_named():
    with pytest.raises(TypeError, match="leaf 1 of dtype int8"):
        layout_of([jnp.zeros(2, jnp.float32), jnp.zeros(2, jnp.int8)])


def test_update_writes_the_changed_leaves_and_equals_a_fresh_pack():
    state = _scene()

    def moved(packed):
        old = unpack(packed)
        new = dataclasses.replace(old, bodies=dataclasses.replace(old.bodies, position=old.bodies.position + 1.0))
        return update(packed, old, new), pack(new)

    updated, fresh = jax2d.jit(moved)(jax2d.jit(pack)(state))
    np.testing.assert_array_equal(np.asarray(updated.buffer), np.asarray(fresh.buffer))
    np.testing.assert_allclose(unpack_host(updated).bodies.position, np.asarray(state.bodies.position) + 1.0)
    with pytest.raises(ValueError, match="layout"):
        update(pack(state), state, {"not": jnp.zeros(3)})


def test_packed_step_equals_the_pytree_step_bitwise():
    state, params = _scene(), jax2d.SimParams()
    stepper = jax2d.jit(jax2d.step_compact, static_argnames="config")
    packed, packed_params = jax2d.jit(pack)(state), jax2d.jit(pack)(jax.tree.map(jnp.float32, params))
    rng = np.random.default_rng(0)
    for _ in range(30):
        motor = rng.uniform(-1, 1, (1,)).astype(np.float32)
        thrust = rng.uniform(0, 1, (1,)).astype(np.float32)
        state = STEP(state, params, motor, thrust)
        packed = stepper(packed, packed_params, motor, thrust)
    assert float(np.abs(np.asarray(state.bodies.velocity)).max()) > 0.1  # something moved
    _assert_trees_equal(unpack_host(packed), state)
