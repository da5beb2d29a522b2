"""The per-binding entropy diagnostic: which bindings a level uses, each categorical's entropy, and the command's
split of a real checkpoint's entropy into used and unused bindings (with bad input refused)."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from jax2d import scene
from kinetix.agents import binding_entropy, checkpoint, distributions
from kinetix.agents.ppo import TrainConfig, make_network
from kinetix.bindings import bound_bindings
from kinetix.env import EnvConfig, make_env
from kinetix.level import empty_level, make_level
from kinetix.levels import load_level


def _bound_level():
    """Size l (6 joint and 2 thruster slots): a motor-on joint on binding 2, a motor-off one on binding 1, a
    motor_auto one on binding 3, the other slots inactive on binding 0; one thruster, on binding 1."""
    sim = empty_level("l").sim
    bodies = []
    for k in range(5):
        sim, i = scene.add_rectangle(sim, (0.6 + 0.6 * k, 2.0), 0.4, 0.4)
        bodies.append(i)
    sim, _ = scene.add_revolute_joint(sim, bodies[0], bodies[1], (0.9, 2.0), motor_on=True)
    sim, _ = scene.add_revolute_joint(sim, bodies[1], bodies[2], (1.5, 2.0), motor_on=False)
    sim, _ = scene.add_revolute_joint(sim, bodies[2], bodies[3], (2.1, 2.0), motor_on=True)
    sim, _ = scene.add_thruster(sim, bodies[4], (3.0, 2.0), angle=0.0)
    return make_level(sim, motor_bindings=[2, 1, 3, 0, 0, 0], motor_auto=[0, 0, 1, 0, 0, 0],
                      thruster_bindings=[1, 0])


def test_bound_bindings_counts_driven_joints_and_active_thrusters():
    level = _bound_level()
    # binding 0: only inactive joint slots; 1: a motor-off joint; 3: a motor_auto joint (ignores the action);
    # thruster 0: only inactive thruster slots
    assert np.asarray(bound_bindings(level)).tolist() == [False, False, True, False, False, True]
    assert not np.asarray(bound_bindings(empty_level("s"))).any()
    car = load_level("levels/car_right.json").level
    assert np.asarray(jax2d.jit(bound_bindings)(car)).any()  # jittable, and a playable level uses some binding


def test_binding_entropies_are_each_categoricals_and_sum_to_the_total():
    uniform = jnp.zeros((2, 16))
    expected = [math.log(3)] * 4 + [math.log(2)] * 2
    np.testing.assert_allclose(np.asarray(distributions.binding_entropies(uniform)), [expected] * 2, rtol=1e-6)
    certain = jnp.zeros(16).at[jnp.array([0, 4, 8, 11, 12, 14])].set(100.0)
    np.testing.assert_allclose(np.asarray(distributions.binding_entropies(certain)), np.zeros(6), atol=1e-6)
    outputs = jax.random.normal(jax.random.key(0), (5, 16))
    np.testing.assert_allclose(np.asarray(distributions.binding_entropies(outputs).sum(-1)),
                               np.asarray(distributions.entropy(outputs, "multi_discrete")), rtol=1e-6)


def _save_checkpoint(path, action="multi_discrete"):
    env = make_env(EnvConfig("s", action=action), empty_level("s"))
    config = TrainConfig(width=16, hidden=32)
    obs, _ = env.reset(jax.random.key(0))
    params = make_network(config, action).init(jax.random.key(1), jax.tree.map(lambda x: x[None], obs))
    checkpoint.save(path, params["params"], config, env.config, {"steps": 0.0})
    return path


def test_a_checkpoint_is_split_into_used_and_unused_bindings(tmp_path, capsys):
    agent = str(_save_checkpoint(tmp_path / "agent"))
    levels = ["levels/car_right.json", "levels/lunar_lander.json"]
    assert binding_entropy.main([agent, "--level", *levels, "--steps", "8", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    used = [np.asarray(bound_bindings(load_level(p).level)) for p in levels]
    assert result["levels_using"] == np.sum(used, 0).tolist()
    assert result["levels_not_using"] == (2 - np.sum(used, 0)).tolist()
    for i, maximum in enumerate(result["maximum"]):
        for side, count in (("used", result["levels_using"][i]), ("unused", result["levels_not_using"][i])):
            value = result[side][i]
            assert (value is None) == (count == 0)
            assert value is None or 0.0 < value <= maximum + 1e-6
    # a freshly initialised policy is close to uniform (the actor head starts small)
    assert 0.9 < result["used_fraction_of_maximum"] <= 1.0 + 1e-6
    assert binding_entropy.main([agent, "--level", "levels/car_right.json", "--steps", "4"]) == 0
    assert "of the uniform policy's" in capsys.readouterr().out


@pytest.mark.parametrize("agent, message", [("random", "no network"), ("/no/such/agent", "unknown agent")])
def test_agents_without_a_network_are_refused(agent, message, capsys):
    assert binding_entropy.main([agent, "--level", "levels/car_right.json"]) == 2
    assert message in capsys.readouterr().err


def test_other_action_spaces_and_missing_levels_are_refused(tmp_path, capsys):
    agent = str(_save_checkpoint(tmp_path / "discrete", action="discrete"))
    assert binding_entropy.main([agent, "--level", "levels/car_right.json"]) == 2
    assert "multi_discrete" in capsys.readouterr().err
    assert binding_entropy.main([agent, "--level", str(tmp_path / "none.json")]) == 2
    assert "does not exist" in capsys.readouterr().err
