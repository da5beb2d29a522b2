"""Env groups (kinetix.agents.ppo.EnvGroup): random-all trains each size class at its own size, with one network."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from kinetix.agents import curricula, ppo
from kinetix.agents.train import size_groups_for, split_evenly
from kinetix.env import EnvConfig, EnvParams, make_env
from kinetix.generate import sample_level


def test_envs_split_into_equal_groups_that_the_devices_and_minibatches_cut_whole():
    assert split_evenly(512, 3) == [170, 171, 171]
    assert split_evenly(512, 3, 2) == [170, 170, 172]
    assert split_evenly(1024, 3) == [341, 341, 342]
    config = ppo.TrainConfig(num_envs=512)  # 64 steps, 4 minibatches: any env count cuts whole
    assert size_groups_for(config, 2) == [170, 170, 172]
    assert size_groups_for(config, 1) == [170, 171, 171]
    odd = ppo.TrainConfig(num_envs=30, num_steps=2, num_minibatches=4)  # each group's 2 E_g samples into 4: E_g even
    assert size_groups_for(odd, 1) == [10, 10, 10]
    assert all((n * 2) % 4 == 0 for n in size_groups_for(odd, 1))
    with pytest.raises(ValueError, match="multiple of 4"):
        size_groups_for(dataclasses.replace(odd, num_envs=34), 4)
    with pytest.raises(ValueError, match="at least 6"):
        size_groups_for(ppo.TrainConfig(num_envs=4), 2)


def _transition_batch(env, config, key, monkeypatch):
    """A rollout's worth of Transitions (T, E) on fresh s levels, from a trainer's own first update's rollout."""
    trainer = ppo.make_train(config, env, EnvParams(max_timesteps=5),
                             curricula.domain_randomisation(lambda k: sample_level(k, "s")))
    runner = jax2d.jit(trainer.init)(key)
    seen = {}
    real = ppo.ppo_update

    def spy(network, action_type, config, train_state, batch, advantages, targets, key, group_configs=None):
        seen.update(batch=batch, advantages=advantages, targets=targets)
        return real(network, action_type, config, train_state, batch, advantages, targets, key, group_configs)

    monkeypatch.setattr(ppo, "ppo_update", spy)
    trainer.update(runner)  # not jitted: the spy keeps concrete arrays
    monkeypatch.setattr(ppo, "ppo_update", real)
    return trainer, runner, seen


def test_a_grouped_update_on_one_minibatch_equals_the_update_of_the_whole_batch(monkeypatch):
    """One epoch of one minibatch: the grouped loss (each group's mean, weighted by its samples, advantages
    normalised over all) is the whole batch's mean loss, so the new parameters agree to rounding."""
    env = make_env(EnvConfig("s"), lambda k: sample_level(k, "s"))
    config = ppo.TrainConfig(num_envs=12, num_steps=6, num_minibatches=1, update_epochs=1, width=16, hidden=32,
                             total_timesteps=72)
    trainer, runner, seen = _transition_batch(env, config, jax.random.key(0), monkeypatch)
    batch, adv, targets = seen["batch"], seen["advantages"], seen["targets"]
    whole, losses = ppo.ppo_update(trainer.network, "multi_discrete", config, runner.train_state, batch, adv, targets,
                                   jax.random.key(1))
    cut = lambda tree, a, b: jax.tree.map(lambda x: x[:, a:b], tree)
    sizes = (4, 8)
    groups = tuple(dataclasses.replace(config, num_envs=n) for n in sizes)
    parts = [(0, 4), (4, 12)]
    grouped, group_losses = ppo.ppo_update(
        trainer.network, "multi_discrete", config, runner.train_state, tuple(cut(batch, a, b) for a, b in parts),
        tuple(cut(adv, a, b) for a, b in parts), tuple(cut(targets, a, b) for a, b in parts), jax.random.key(1),
        groups)
    moved = 0.0
    for a, b, before in zip(jax.tree.leaves(whole.params), jax.tree.leaves(grouped.params),
                            jax.tree.leaves(runner.train_state.params), strict=True):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-4, atol=1e-6)
        moved = max(moved, float(jnp.abs(a - before).max()))
    assert moved > 1e-5  # the update did change the parameters
    # atol: on a first update the actor loss is -mean(normalised advantages), 0 up to the rounding of a sum of 72
    # O(1) terms (1e-7 apart in CI once, -9.5e-8 against 2.6e-8)
    for name in ("value_loss", "actor_loss", "entropy"):
        np.testing.assert_allclose(float(group_losses[name]), float(losses[name]), rtol=1e-4, atol=1e-6)


def test_groups_step_their_own_size_class_and_train_one_network():
    config = ppo.TrainConfig(num_envs=8, num_steps=6, num_minibatches=2, update_epochs=1, width=16, hidden=32,
                             total_timesteps=96)
    groups = []
    for size, count in (("s", 4), ("m", 4)):
        generator = lambda k, size=size: sample_level(k, size)
        groups.append(ppo.EnvGroup(size, make_env(EnvConfig(size), generator),
                                   curricula.domain_randomisation(generator), count))
    trainer = ppo.make_train(config, groups[-1].env, EnvParams(max_timesteps=4), groups[-1].curriculum,
                             groups=tuple(groups))
    runner = jax2d.jit(trainer.init)(jax.random.key(0))
    s_bodies = runner.env_state[0].level.sim.bodies.active.shape
    m_bodies = runner.env_state[1].level.sim.bodies.active.shape
    assert s_bodies == (4, 7) and m_bodies == (4, 9)  # each group at its own capacity, no padding
    before = runner.train_state.params
    runner, metrics = jax2d.jit(trainer.update)(runner)
    assert {"solve_rate_s", "solve_rate_m"} <= set(metrics)
    assert float(metrics["env_steps"]) == 48 and float(metrics["episodes"]) > 0  # max 4 steps: every env ends once
    assert int(runner.update_index) == 1
    assert runner.env_state[0].level.sim.bodies.active.shape == (4, 7)
    after = runner.train_state.params
    assert any(not np.allclose(a, b) for a, b in zip(jax.tree.leaves(before), jax.tree.leaves(after), strict=True))
    with pytest.raises(ValueError, match="hold 8 environments, num_envs is 12"):
        ppo.make_train(dataclasses.replace(config, num_envs=12), groups[-1].env, EnvParams(), groups[-1].curriculum,
                       groups=tuple(groups))


def test_bench_train_measures_random_all_in_groups_and_padded():
    from kinetix.agents import bench
    from kinetix.cli import build_parser

    args = build_parser().parse_args(["bench", "train", "--sizes", "all,all-padded"])
    assert args.sizes == ["all", "all-padded"]
    with pytest.raises(SystemExit):
        build_parser().parse_args(["bench", "train", "--sizes", "everything"])
    result = bench.measure("all", num_envs=6, num_steps=2, chunks=1, updates_per_call=1)
    assert result["size"] == "all" and result["env_steps"] == 12 and result["steps_per_second"] > 0
