"""The network-health diagnostic: dead units per hidden layer and the information the policy's choice carries about
the state, on real checkpoints; a relu layer killed by hand reads 100% dead and a policy that cannot see the state
reads 0 nats; bad input is refused."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kinetix.agents import checkpoint, health
from kinetix.agents.networks import ActorCritic, EntityEncoder
from kinetix.agents.ppo import TrainConfig, Transition, make_network, ppo_loss
from kinetix.agents.train import dead_actor_warning
from kinetix.env import EnvConfig, make_env
from kinetix.level import empty_level
from kinetix.levels import load_level

LEVELS = ["levels/car_right.json", "levels/thruster_maze.json", "levels/seesaw.json"]  # all m: one compile


def _params(config, action="multi_discrete"):
    env = make_env(EnvConfig("s", action=action), empty_level("s"))
    obs, _ = env.reset(jax.random.key(0))
    params = make_network(config, action).init(jax.random.key(1), jax.tree.map(lambda x: x[None], obs))["params"]
    return env, params


def _save(path, config, params, env):
    checkpoint.save(path, params, config, env.config, {"steps": 0.0})
    return str(path)


def _run(capsys, agent, *extra):
    assert health.main([agent, "--level", *LEVELS, "--steps", "8", "--json", *extra]) == 0
    return json.loads(capsys.readouterr().out)


def test_every_hidden_layer_is_reported_and_a_sharpened_policy_depends_on_the_state(tmp_path, capsys):
    config = TrainConfig(width=16, hidden=32, activation="tanh")
    env, params = _params(config)
    # a freshly initialised head is near uniform on purpose (orthogonal 0.01); scale it so the state shows
    params["Heads_0"]["Dense_2"]["kernel"] = params["Heads_0"]["Dense_2"]["kernel"] * 300.0
    result = _run(capsys, _save(tmp_path / "agent", config, params, env))
    assert result["activation"] == "tanh" and result["states"] > 0
    expected = {"actor_0", "actor_1", "critic_0", "critic_1", "polygons_0", "polygons_1", "circles_0", "circles_1",
                "joints_0", "joints_1", "thrusters_0", "thrusters_1", "mix_0"}
    assert set(result["layers"]) == expected
    assert result["layers"]["actor_1"]["units"] == 32 and result["layers"]["polygons_0"]["units"] == 16
    for layer in result["layers"].values():
        assert 0.0 <= layer["dead"] < 0.5 and 0.5 < layer["active"] <= 1.0  # a fresh tanh network is alive
    used = [x for x in result["information"] if x is not None]
    assert used and all(x >= 0.0 for x in used) and max(used) > 1e-3
    assert result["information_mean"] == pytest.approx(float(np.mean(used)))


def test_a_dead_relu_layer_reads_dead_and_its_policy_carries_no_information(tmp_path, capsys):
    config = TrainConfig(width=16, hidden=32, activation="relu")
    env, params = _params(config)
    params["Heads_0"]["Dense_2"]["kernel"] = params["Heads_0"]["Dense_2"]["kernel"] * 300.0
    healthy = _run(capsys, _save(tmp_path / "healthy", config, params, env))
    # what happened to the first general run: every unit of the actor's second layer negative on every input
    params["Heads_0"]["Dense_1"]["bias"] = jnp.full_like(params["Heads_0"]["Dense_1"]["bias"], -1e3)
    dead = _run(capsys, _save(tmp_path / "dead", config, params, env))
    assert dead["activation"] == "relu"
    assert dead["layers"]["actor_1"]["dead"] == 1.0 and dead["layers"]["actor_1"]["active"] == 0.0
    assert healthy["layers"]["actor_1"]["dead"] < 1.0
    assert dead["layers"]["critic_1"]["dead"] < 1.0  # the critic's trunk is untouched
    assert max(x for x in healthy["information"] if x is not None) > 1e-3
    assert all(x is None or x < 1e-6 for x in dead["information"])  # one fixed distribution on every state
    assert health.main([str(tmp_path / "dead"), "--level", *LEVELS, "--steps", "8"]) == 0  # the table
    table = capsys.readouterr().out
    assert "relu, 3 levels" in table and any(line.split()[:3] == ["actor_1", "32", "100.0%"]
                                             for line in table.splitlines())


def test_slope_marks_dead_units_for_either_activation():
    pre = jnp.array([-5.0, -0.1, 0.0, 0.1, 5.0])
    assert (np.asarray(health.slope("relu", pre)) >= health.DEAD_SLOPE).tolist() == [False, False, False, True, True]
    assert (np.asarray(health.slope("tanh", pre)) >= health.DEAD_SLOPE).tolist() == [False, True, True, True, False]


def test_bad_agents_are_refused(tmp_path, capsys):
    config = TrainConfig(width=16, hidden=32)
    env, params = _params(config, action="continuous")
    agent = _save(tmp_path / "continuous", config, params, env)
    assert health.main([agent, "--level", LEVELS[0]]) == 2
    assert "multi_discrete" in capsys.readouterr().err
    assert health.main(["random", "--level", LEVELS[0]]) == 2
    assert "no network" in capsys.readouterr().err
    assert health.main([str(tmp_path / "missing"), "--level", LEVELS[0]]) == 2
    assert "unknown agent" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    assert health.main(["general", "--level", str(bad)]) == 2
    assert "bad.json" in capsys.readouterr().err


def test_sown_pre_activations_do_not_change_the_parameters_or_outputs():
    obs = make_env(EnvConfig("s"), empty_level("s")).reset(jax.random.key(0))[0]
    batch = jax.tree.map(lambda x: jnp.stack([x, x]), obs)
    network = ActorCritic(width=16, hidden=32)
    params = network.init(jax.random.key(1), batch)
    assert set(params) == {"params"}  # intermediates are only collected when asked for
    plain = network.apply(params, batch)
    collected, state = network.apply(params, batch, mutable=["intermediates"])
    for a, b in zip(jax.tree.leaves(plain), jax.tree.leaves(collected), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert state["intermediates"]  # and then they are there


def _loss_health(config, params, samples=16):
    """The heads' dead shares that ppo_loss reports on a minibatch of states of a random episode of car_right."""
    level = load_level(LEVELS[0])
    env = make_env(EnvConfig("m"), level.level)  # car_right is an m level
    key = jax.random.key(3)
    obs, state = env.reset(key)
    observations = []
    for i in range(samples):
        observations.append(obs)
        action = env.action_space.sample(jax.random.fold_in(key, i))
        obs, state, *_ = env.step(jax.random.fold_in(key, 100 + i), state, action)
    batch_obs = jax.tree.map(lambda *xs: jnp.stack(xs), *observations)
    zeros = jnp.zeros(samples)
    batch = Transition(batch_obs, jnp.zeros((samples, 6), jnp.int32), zeros, zeros, zeros, zeros, zeros, zeros)
    _, aux = ppo_loss(make_network(config, "multi_discrete"), "multi_discrete", config, params, batch, zeros, zeros)
    return float(aux["actor_dead"]), float(aux["critic_dead"])


def test_training_reports_a_dead_actor_layer_and_warns_about_it():
    fresh = TrainConfig(width=16, hidden=32, activation="tanh")
    assert _loss_health(fresh, _params(fresh)[1]) == (0.0, 0.0)  # no fresh tanh unit saturates
    config = TrainConfig(width=16, hidden=32, activation="relu")
    params = _params(config)[1]
    params["Heads_0"]["Dense_1"]["bias"] = jnp.full_like(params["Heads_0"]["Dense_1"]["bias"], -1e3)
    actor, critic = _loss_health(config, params)
    assert actor == 1.0 and critic < 1.0  # the actor's second layer is dead, the critic's trunk is not
    half = jnp.arange(32) < 16  # half of the critic's second layer (Dense_3, Dense_4 are the critic's)
    params["Heads_0"]["Dense_4"]["bias"] = jnp.where(half, -1e3, params["Heads_0"]["Dense_4"]["bias"])
    assert _loss_health(config, params)[1] >= 0.5
    assert dead_actor_warning({"update": 7, "actor_dead": 0.4}, "relu") is None
    warning = dead_actor_warning({"update": 7, "actor_dead": 1.0}, "relu")
    assert "update 7" in warning and "100%" in warning and "kinetix.agents.health" in warning


def test_the_pooled_norm_keeps_the_heads_inputs_at_unit_scale_however_the_encoder_grows():
    """The summary the heads read: with pooled_norm it has unit spread even when the encoder's weights grow 10x (as
    a long run's residual stream does); without it, it grows with them and would saturate the heads' tanh units."""
    env = make_env(EnvConfig("m"), load_level(LEVELS[0]).level)  # car_right, an m level
    obs, _ = env.reset(jax.random.key(0))

    def spread(pooled_norm: bool, scale: float) -> float:
        encoder = EntityEncoder(width=16, pooled_norm=pooled_norm)
        params = encoder.init(jax.random.key(1), obs)["params"]
        params = jax.tree_util.tree_map_with_path(
            lambda path, x: x * scale if "kernel" in jax.tree_util.keystr(path) else x, params)
        return float(jnp.std(encoder.apply({"params": params}, obs)))

    assert abs(spread(True, 1.0) - 1.0) < 1e-3 and abs(spread(True, 10.0) - 1.0) < 1e-3
    assert spread(False, 10.0) > 5 * spread(False, 1.0)
