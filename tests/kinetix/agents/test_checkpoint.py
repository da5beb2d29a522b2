"""Checkpoints round-trip exactly; load_policy builds working policies and refuses mismatched envs."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from kinetix.agents import checkpoint
from kinetix.agents.checkpoint import CheckpointError
from kinetix.agents.policy import load_policy
from kinetix.agents.ppo import TrainConfig, make_network
from kinetix.env import EnvConfig, make_env
from kinetix.level import empty_level


@pytest.fixture(scope="module")
def env():
    return make_env(EnvConfig("s"), empty_level("s"))


@pytest.fixture(scope="module")
def trained(env, tmp_path_factory):
    config = TrainConfig(width=16, hidden=32)
    network = make_network(config, "multi_discrete")
    obs, _ = env.reset(jax.random.key(0))
    params = network.init(jax.random.key(1), jax.tree.map(lambda x: x[None], obs))["params"]
    path = checkpoint.save(tmp_path_factory.mktemp("ckpt") / "agent", params, config, env.config, {"note": "test"})
    return path, params, config, network, obs


def test_round_trip_is_exact(trained, env):
    path, params, config, _, _ = trained
    loaded = checkpoint.load(path)
    assert loaded.train_config == config
    assert loaded.env == checkpoint.env_description(env.config)
    assert loaded.info == {"note": "test"}
    flat, tree = jax.tree.flatten(params)
    loaded_flat, loaded_tree = jax.tree.flatten(loaded.params)
    assert tree == loaded_tree
    for a, b in zip(flat, loaded_flat, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_policy_from_checkpoint_matches_the_network(trained, env):
    path, params, _, network, obs = trained
    policy = load_policy(str(path), env, deterministic=True)
    action, value = jax2d.jit(policy.act)(jax.random.key(0), obs)
    outputs, expected_value = network.apply({"params": params}, jax.tree.map(lambda x: x[None], obs))
    # jitted against eager: XLA fuses the LayerNorms' reductions in another order (a few float32 ulps)
    np.testing.assert_allclose(value, expected_value[0], rtol=1e-5, atol=1e-7)
    assert env.action_space.contains(np.asarray(action))


def test_apply_takes_the_parameters_as_an_argument_and_signatures_group_equal_programs(trained, env):
    path, params, _, network, obs = trained
    policy = load_policy(str(path), env, deterministic=True)
    apply = jax2d.jit(policy.apply)
    action, value = apply(policy.params, jax.random.key(0), obs)
    np.testing.assert_array_equal(action, policy.act(jax.random.key(0), obs)[0])
    # Other parameters through the same compiled function give that network's value.
    other = jax.tree.map(lambda x: x * 0.5, policy.params)
    _, other_value = apply(other, jax.random.key(0), obs)
    _, expected = network.apply({"params": other}, jax.tree.map(lambda x: x[None], obs))
    np.testing.assert_allclose(other_value, expected[0], rtol=1e-5)
    assert load_policy(str(path), env, deterministic=True).signature == policy.signature
    assert load_policy(str(path), env).signature != policy.signature  # sampling is another program
    assert load_policy("noop", env).signature != policy.signature


def test_noop_and_random_policies(env):
    obs, _ = env.reset(jax.random.key(0))
    noop = load_policy("noop", env)
    action, value = jax2d.jit(noop.act)(jax.random.key(0), obs)
    np.testing.assert_array_equal(action, np.zeros(6))
    assert float(value) == 0.0
    rand = jax2d.jit(load_policy("random", env).act)
    actions = np.stack([np.asarray(rand(jax.random.key(i), obs)[0]) for i in range(20)])
    assert all(env.action_space.contains(a) for a in actions)
    assert len({tuple(a) for a in actions}) > 1


def test_mismatched_env_and_bad_paths_are_refused(trained, tmp_path):
    path = trained[0]
    with pytest.raises(CheckpointError, match="observations"):
        load_policy(str(path), make_env(EnvConfig("s", observation="flat"), empty_level("s")))
    with pytest.raises(CheckpointError, match="unknown agent"):
        load_policy(str(tmp_path / "missing"), make_env(EnvConfig("s"), empty_level("s")))
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "config.json").write_text(json.dumps({"format": "something else"}))
    (tmp_path / "broken" / "params.msgpack").write_bytes(b"")
    with pytest.raises(CheckpointError, match="not a kinetix-agent"):
        checkpoint.load(tmp_path / "broken")


def test_save_refuses_to_replace_a_foreign_directory(trained, tmp_path, env):
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    with pytest.raises(CheckpointError, match="not a checkpoint"):
        checkpoint.save(foreign, trained[1], trained[2], env.config)
    assert (foreign / "notes.txt").read_text() == "keep me"


def test_entity_policy_runs_on_every_size(trained):
    path = trained[0]
    for size in ("s", "m", "l"):
        env = make_env(EnvConfig(size), empty_level(size))
        obs, _ = env.reset(jax.random.key(0))
        action, value = load_policy(str(path), env).act(jax.random.key(0), obs)
        assert action.shape == (6,) and jnp.isfinite(value)


def _saved_without(field: str, config: TrainConfig, env, where):
    """A checkpoint of a fresh `config` network whose config.json lacks `field`, as files from before it existed;
    returns (path, network, params, obs, batch)."""
    network = make_network(config, "multi_discrete")
    obs, _ = env.reset(jax.random.key(0))
    batch = jax.tree.map(lambda x: x[None], obs)
    params = network.init(jax.random.key(1), batch)["params"]
    path = checkpoint.save(where, params, config, env.config)
    document = json.loads((path / "config.json").read_text())
    del document["train"][field]
    (path / "config.json").write_text(json.dumps(document))
    return path, network, params, obs, batch


def test_a_checkpoint_from_before_the_activation_field_loads_as_relu(env, tmp_path):
    """Every network saved before TrainConfig had `activation` was relu; its config.json has no such field."""
    path, network, params, obs, batch = _saved_without(
        "activation", TrainConfig(width=16, hidden=32, activation="relu"), env, tmp_path / "old")
    assert checkpoint.load(path).train_config.activation == "relu"
    _, value = load_policy(str(path), env, deterministic=True).act(jax.random.key(0), obs)
    np.testing.assert_allclose(value, network.apply({"params": params}, batch)[1][0], rtol=1e-6)
    tanh_value = make_network(TrainConfig(width=16, hidden=32), "multi_discrete").apply({"params": params}, batch)[1]
    assert abs(float(tanh_value[0]) - float(value)) > 1e-6  # the activation matters: loading as tanh would show


def test_a_checkpoint_from_before_the_pooled_norm_field_loads_without_the_norm(env, tmp_path):
    """Networks saved before TrainConfig had `pooled_norm` have no LayerNorm on the pooled summary (the tanh run
    sfl-tanh among them); their config.json has no such field, and they must load and act as they were saved."""
    path, network, params, obs, batch = _saved_without(
        "pooled_norm", TrainConfig(width=16, hidden=32, pooled_norm=False), env, tmp_path / "old")
    assert checkpoint.load(path).train_config.pooled_norm is False
    _, value = load_policy(str(path), env, deterministic=True).act(jax.random.key(0), obs)
    np.testing.assert_allclose(value, network.apply({"params": params}, batch)[1][0], rtol=1e-6)
    with_norm = make_network(TrainConfig(width=16, hidden=32), "multi_discrete").init(jax.random.key(1), batch)
    assert jax.tree.structure(with_norm["params"]) != jax.tree.structure(params)  # the default has the extra norm


@pytest.mark.parametrize("bad", [1, "yes", None])
def test_a_pooled_norm_that_is_not_a_bool_is_refused(bad):
    with pytest.raises(ValueError, match="pooled_norm must be true or false"):
        TrainConfig(pooled_norm=bad)


def test_an_unknown_activation_is_refused():
    with pytest.raises(ValueError, match="unknown activation 'gelu'"):
        TrainConfig(activation="gelu")
