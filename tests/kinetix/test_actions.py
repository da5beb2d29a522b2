"""Action spaces: every action type's mapping to binding values, and bindings reaching joints and thrusters."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from jax2d import scene
from kinetix.actions import (
    ACTION_TYPES,
    action_space,
    binding_values,
    level_actions,
    noop_action,
    policy_outputs,
    sample_random_action,
)
from kinetix.env import EnvConfig
from kinetix.level import empty_level, make_level

# discrete action -> (motor binding values, thruster binding values), written out by hand
DISCRETE_TABLE = {
    0: ([-1, 0, 0, 0], [0, 0]),
    1: ([1, 0, 0, 0], [0, 0]),
    2: ([0, -1, 0, 0], [0, 0]),
    3: ([0, 1, 0, 0], [0, 0]),
    4: ([0, 0, -1, 0], [0, 0]),
    5: ([0, 0, 1, 0], [0, 0]),
    6: ([0, 0, 0, -1], [0, 0]),
    7: ([0, 0, 0, 1], [0, 0]),
    8: ([0, 0, 0, 0], [0, 0]),
    9: ([0, 0, 0, 0], [1, 0]),
    10: ([0, 0, 0, 0], [0, 1]),
}

MULTI_DISCRETE_TABLE = [
    ([0, 0, 0, 0, 0, 0], [0, 0, 0, 0], [0, 0]),
    ([1, 2, 0, 1, 1, 0], [1, -1, 0, 1], [1, 0]),
    ([2, 2, 2, 2, 0, 1], [-1, -1, -1, -1], [0, 1]),
    ([0, 1, 1, 0, 1, 1], [0, 1, 1, 0], [1, 1]),
    ([3, -1, 0, 0, 2, 0], [0, 0, 0, 0], [0, 0]),  # out of range: off, never another value
]

CONTINUOUS_TABLE = [
    ([0.5, -0.25, 0.0, 1.0, 0.3, 1.0], [0.5, -0.25, 0.0, 1.0], [0.3, 1.0]),
    ([3.0, -7.0, 1.5, -1.0, -0.5, 2.0], [1.0, -1.0, 1.0, -1.0], [0.0, 1.0]),
    ([np.nan, 0.0, 0.0, 0.0, np.nan, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0]),
]


def check(action, action_type, motor, thrust):
    got_motor, got_thrust = jax2d.jit(binding_values, static_argnums=1)(action, action_type)
    assert got_motor.shape == (4,) and got_thrust.shape == (2,)
    assert got_motor.dtype == got_thrust.dtype == jnp.float32
    np.testing.assert_array_equal(got_motor, np.asarray(motor, np.float32), err_msg=f"{action_type} {action}")
    np.testing.assert_array_equal(got_thrust, np.asarray(thrust, np.float32), err_msg=f"{action_type} {action}")


@pytest.mark.parametrize("action", sorted(DISCRETE_TABLE))
def test_discrete(action):
    check(jnp.asarray(action, jnp.int32), "discrete", *DISCRETE_TABLE[action])


def test_discrete_out_of_range_is_a_noop():
    for action in (-1, 11, 100):
        check(jnp.asarray(action, jnp.int32), "discrete", [0, 0, 0, 0], [0, 0])


@pytest.mark.parametrize("row", MULTI_DISCRETE_TABLE)
def test_multi_discrete(row):
    action, motor, thrust = row
    check(jnp.asarray(action, jnp.int32), "multi_discrete", motor, thrust)


@pytest.mark.parametrize("row", CONTINUOUS_TABLE)
def test_continuous(row):
    action, motor, thrust = row
    check(jnp.asarray(action, jnp.float32), "continuous", motor, thrust)


def test_spaces_noop_and_random_actions():
    assert action_space("multi_discrete").nvec == (3, 3, 3, 3, 2, 2)
    assert action_space("discrete").n == 11
    box = action_space("continuous")
    assert box.shape == (6,) and box.low == (-1, -1, -1, -1, 0, 0) and box.high == 1.0
    assert [policy_outputs(t) for t in ACTION_TYPES] == [16, 11, 6]
    for action_type in ACTION_TYPES:
        config = EnvConfig("s", action=action_type)
        motor, thrust = binding_values(noop_action(config), action_type)
        assert not np.any(motor) and not np.any(thrust), action_type
        space = action_space(action_type)
        samples = jax.vmap(lambda k: sample_random_action(k, config))(jax.random.split(jax.random.PRNGKey(0), 400))
        s = np.asarray(samples)
        assert all(space.contains(x) for x in s), action_type
        if action_type == "multi_discrete":  # every value of every entry shows up in 400 uniform draws
            for i, n in enumerate(space.nvec):
                assert set(np.unique(s[:, i])) == set(range(n))
        elif action_type == "discrete":
            assert set(np.unique(s)) == set(range(11))
        else:  # motors sample [-1, 1], thrusters [0, 1]
            assert s[:, :4].min() < -0.9 and s[:, 4:].min() >= 0.0 and s.max() > 0.9
    with pytest.raises(ValueError, match="action type"):
        action_space("keyboard")


@pytest.fixture(scope="module")
def bound_level():
    """Size l: a chain of 7 bodies and 6 motor joints with bindings [0, 1, 0, 2, 3, 1], joint 5 motor_auto,
    and 2 thrusters on bindings [1, 0]."""
    sim = empty_level("l").sim
    bodies = []
    for k in range(4):
        sim, i = scene.add_rectangle(sim, (0.6 + 0.6 * k, 2.0), 0.4, 0.4)
        bodies.append(i)
    for k in range(3):
        sim, i = scene.add_circle(sim, (3.0 + 0.5 * k, 2.0), 0.15)
        bodies.append(i)
    for j in range(6):
        a, b = bodies[j], bodies[j + 1]
        sim, _ = scene.add_revolute_joint(sim, a, b, (0.9 + 0.6 * j, 2.0), motor_on=True)
    sim, _ = scene.add_thruster(sim, bodies[0], (0.6, 2.0), angle=0.0)
    sim, _ = scene.add_thruster(sim, bodies[2], (1.8, 2.0), angle=1.0)
    return make_level(sim, motor_bindings=[0, 1, 0, 2, 3, 1], motor_auto=[0, 0, 0, 0, 0, 1],
                      thruster_bindings=[1, 0])


@pytest.mark.parametrize("action_type", ACTION_TYPES)
def test_joints_sharing_a_binding_get_the_same_action(bound_level, action_type):
    bindings = np.asarray(bound_level.motor_bindings)
    auto = np.asarray(bound_level.motor_auto)
    @jax2d.jit
    def one(key):
        action = sample_random_action(key, action_type)
        return binding_values(action, action_type), level_actions(bound_level, action, action_type)

    for key in jax.random.split(jax.random.PRNGKey(1), 30):
        (motor_values, thrust_values), (motor, thrust) = one(key)
        assert motor.shape == (6,) and thrust.shape == (2,)
        expected = np.where(auto, 1.0, np.asarray(motor_values)[bindings])
        np.testing.assert_array_equal(motor, expected)
        np.testing.assert_array_equal(thrust, np.asarray(thrust_values)[[1, 0]])
        assert motor[0] == motor[2] and motor[5] == 1.0  # joints 0 and 2 share binding 0; joint 5 is auto


def test_discrete_action_reaches_the_bound_joints(bound_level):
    # Action 1 drives binding 0 at +1: joints 0 and 2; joint 5 is motor_auto and always +1.
    motor, thrust = level_actions(bound_level, jnp.asarray(1), "discrete")
    np.testing.assert_array_equal(motor, [1, 0, 1, 0, 0, 1])
    np.testing.assert_array_equal(thrust, [0, 0])
    # Action 10 fires thruster binding 1, which thruster 0 listens to.
    motor, thrust = level_actions(bound_level, jnp.asarray(10), "discrete")
    np.testing.assert_array_equal(motor, [0, 0, 0, 0, 0, 1])
    np.testing.assert_array_equal(thrust, [1, 0])
