"""The network in parts on the CPU (kinetix.agents.parts) and the rollout's truncated-only successor values give the
numbers of one whole pass (to float rounding)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from kinetix.agents import curricula, parts, ppo
from kinetix.env import EnvConfig, EnvParams, make_env
from kinetix.generate import sample_level


@pytest.fixture
def small_parts(monkeypatch):
    monkeypatch.setattr(parts, "CPU_PART", 8)


def test_parts_split_evenly():
    assert parts._parts(512) == 2 and parts._parts(256) == 1 and parts._parts(8192) == 32
    assert parts._parts(300) == 2  # 150 + 150
    assert parts._parts(257) == 257 or 257 % parts._parts(257) == 0  # a prime splits into ones or not at all


def test_forward_in_parts_equals_one_pass(small_parts):
    x = jax.random.normal(jax.random.key(0), (64, 5, 3))
    w = jax.random.normal(jax.random.key(1), (3, 7))
    apply = lambda b: (jnp.tanh(b @ w).sum(1), b.mean((1, 2)))
    whole = apply(x)
    split = jax2d.jit(lambda b: parts.forward(apply, b))(x)
    assert parts._parts(64) == 8
    for a, b in zip(whole, split, strict=True):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-6, atol=1e-6)


def test_mean_grad_in_parts_equals_whole_batch_gradient(small_parts):
    x = jax.random.normal(jax.random.key(0), (48, 4))
    y = jax.random.normal(jax.random.key(1), (48,))
    params = {"w": jax.random.normal(jax.random.key(2), (4,)), "b": jnp.asarray(0.3)}

    def loss(p, batch):
        bx, by = batch
        err = jnp.tanh(bx @ p["w"] + p["b"]) - by
        return (err**2).mean(), {"abs": jnp.abs(err).mean()}

    (_, aux), grads = jax.value_and_grad(loss, has_aux=True)(params, (x, y))
    aux_parts, grads_parts = jax2d.jit(lambda p, b: parts.mean_grad(loss, p, b))(params, (x, y))
    assert parts._parts(48) == 6
    np.testing.assert_allclose(float(aux_parts["abs"]), float(aux["abs"]), rtol=1e-6)
    for name in grads:
        np.testing.assert_allclose(np.asarray(grads_parts[name]), np.asarray(grads[name]), rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("wanted_rows", [[], [3], [0, 5, 63], list(range(0, 64, 3))])
def test_values_where_equals_every_row(wanted_rows):
    obs = {"a": jax.random.normal(jax.random.key(0), (64, 3))}
    wanted = jnp.zeros((64,), bool).at[jnp.asarray(wanted_rows, jnp.int32)].set(True)
    value_fn = lambda o: o["a"].sum(-1) + 1.0
    got = jax2d.jit(lambda o, w: ppo._values_where(value_fn, o, w))(obs, wanted)
    expected = jnp.where(wanted, value_fn(obs), 0.0)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(expected))  # 4 gathered rows, or the fallback (22)


def test_update_in_parts_equals_one_pass(monkeypatch):
    """A whole PPO update (rollout with time limits, GAE, minibatch epochs) in parts of 8 against one pass."""
    generator = lambda key: sample_level(key, "s")
    env = make_env(EnvConfig("s"), generator)
    config = ppo.TrainConfig(num_envs=16, num_steps=8, num_minibatches=2, update_epochs=1, width=16, hidden=32,
                             total_timesteps=128)
    params = EnvParams(max_timesteps=5)  # truncations inside the rollout
    results = []
    for part in (1024, 8):
        monkeypatch.setattr(parts, "CPU_PART", part)
        trainer = ppo.make_train(config, env, params, curricula.domain_randomisation(generator))
        runner = jax2d.jit(trainer.init)(jax.random.key(0))
        runner, metrics = jax2d.jit(trainer.update)(runner)
        results.append((runner, metrics))
    (one, m_one), (split, m_split) = results
    assert float(m_one["episodes"]) == float(m_split["episodes"]) > 0
    for a, b in zip(jax.tree.leaves(one.train_state.params), jax.tree.leaves(split.train_state.params), strict=True):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(float(m_split["value_loss"]), float(m_one["value_loss"]), rtol=1e-4)


def test_successor_values_are_those_of_the_true_successor(monkeypatch):
    """bootstrap_value: V(next observation) inside an episode, and where the time limit ended one, V(its final
    observation): not the value of the reset observation the env continues from."""
    generator = lambda key: sample_level(key, "s")
    env = make_env(EnvConfig("s"), generator)
    config = ppo.TrainConfig(num_envs=8, num_steps=6, num_minibatches=1, update_epochs=1, width=16, hidden=32,
                             total_timesteps=48)
    seen = {}
    real_gae = ppo.compute_gae

    def spy(reward, value, bootstrap_value, terminated, done, gamma, lam):
        seen.update(value=value, bootstrap=bootstrap_value, terminated=terminated, done=done)
        return real_gae(reward, value, bootstrap_value, terminated, done, gamma, lam)

    monkeypatch.setattr(ppo, "compute_gae", spy)
    trainer = ppo.make_train(config, env, EnvParams(max_timesteps=4), curricula.domain_randomisation(generator))
    runner = jax2d.jit(trainer.init)(jax.random.key(1))
    trainer.update(runner)  # not jitted: the spy sees concrete arrays
    value, bootstrap = np.asarray(seen["value"]), np.asarray(seen["bootstrap"])
    done, terminated = np.asarray(seen["done"]) > 0, np.asarray(seen["terminated"]) > 0
    going, truncated = ~done[:-1], (done & ~terminated)[:-1]
    assert going.any() and truncated.any()
    np.testing.assert_allclose(bootstrap[:-1][going], value[1:][going], rtol=1e-6)
    # the final observation of a timed-out episode is another state than the fresh level the env resets to
    assert not np.allclose(bootstrap[:-1][truncated], value[1:][truncated])


@pytest.mark.parametrize("num_envs,num_steps,num_minibatches", [(16, 8, 4), (12, 4, 2), (5, 4, 4)])
def test_shuffle_takes_every_sample_once_and_evenly_from_each_block(num_envs, num_steps, num_minibatches):
    config = ppo.TrainConfig(num_envs=num_envs, num_steps=num_steps, num_minibatches=num_minibatches)
    blocks = ppo.shuffle_blocks(config)
    ids = jnp.arange(num_steps * num_envs).reshape(num_steps, num_envs)  # sample id = t * E + e
    shuffled = np.asarray(ppo.shuffle_minibatches({"id": ids}, jax.random.key(3), config)["id"])
    assert shuffled.shape == (num_minibatches, num_steps * num_envs // num_minibatches)
    assert sorted(shuffled.ravel().tolist()) == list(range(num_steps * num_envs))
    env_block = (shuffled % num_envs) // (num_envs // blocks)
    for row in env_block:  # every minibatch takes as many samples from each block of envs
        assert np.bincount(row, minlength=blocks).tolist() == [len(row) // blocks] * blocks
    again = np.asarray(ppo.shuffle_minibatches({"id": ids}, jax.random.key(4), config)["id"])
    assert not np.array_equal(again, shuffled)  # another key, another order
