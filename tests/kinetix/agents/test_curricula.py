"""The curricula's bookkeeping on hand-made feedback: sfl keeps the most learnable levels, plr ranks by score,
admits fresh levels that beat the buffer and keeps every environment's level id pointing at the right slot."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from kinetix.agents import curricula
from kinetix.agents.curricula import CurriculumConfig, Feedback
from kinetix.generate import sample_level


def generator(key):
    return sample_level(key, "s")


@jax2d.jit
def generate(keys):
    return jax.vmap(generator)(keys)


def jitted(curriculum):
    """(init, sample, update) jitted: the generator is far too slow op by op."""
    return (jax2d.jit(curriculum.init), jax2d.jit(curriculum.sample, static_argnums=2), jax2d.jit(curriculum.update))


def gravity_tag(levels):
    """Each level's generated body positions, as a fingerprint to follow levels through the buffer."""
    return np.asarray(levels.sim.bodies.position).reshape(levels.sim.bodies.position.shape[0], -1)


def test_sfl_keeps_the_most_learnable_levels():
    config = CurriculumConfig(buffer_size=2, candidates=4, attempts=1, refresh_every=1)
    rates = jnp.asarray([0.0, 0.5, 1.0, 0.2])  # learnability p(1-p): 0, .25, 0, .16

    def solve_rate_fn(key, params, levels, attempts):
        return rates

    init, sample, update = jitted(curricula.sfl(generator, solve_rate_fn, config))
    state = init(jax.random.key(0))
    env_levels = generate(jax.random.split(jax.random.key(5), 3))
    feedback = Feedback(None, jnp.zeros((2, 3), jnp.int32), jnp.zeros((2, 3)), jnp.asarray([0, 1, -1], jnp.int32),
                        env_levels, jnp.asarray(0, jnp.int32))
    key = jax.random.key(1)
    state, env_ids = update(key, state, feedback)
    np.testing.assert_allclose(state["scores"], [0.25, 0.16], rtol=1e-6)
    candidates = generate(jax.random.split(jax.random.split(key)[0], 4))
    np.testing.assert_array_equal(gravity_tag(state["levels"]), gravity_tag(candidates)[[1, 3]])
    assert np.all(np.asarray(env_ids) == -2)  # a refresh detaches running episodes from the buffer
    levels, ids = sample(jax.random.key(2), state, 64)
    assert set(np.asarray(ids).tolist()) <= {-1, 0, 1} and (np.asarray(ids) >= 0).any()


def test_curriculum_sizes_are_checked_with_a_clear_message():
    with pytest.raises(ValueError, match="buffer size must be a positive integer, got 0"):
        CurriculumConfig(buffer_size=0)
    with pytest.raises(ValueError, match="replay probability must be in"):
        CurriculumConfig(replay_prob=1.5)
    with pytest.raises(ValueError, match="best 8 of 4 scored levels"):
        curricula.sfl(generator, lambda *args: None, CurriculumConfig(buffer_size=8, candidates=4))
    curricula.plr(generator, CurriculumConfig(buffer_size=256))  # plr scores no candidates: any buffer size


def test_plr_scores_admits_and_remaps():
    config = CurriculumConfig(buffer_size=2, replay_prob=1.0)
    init, sample, update = jitted(curricula.plr(generator, config))
    state = init(jax.random.key(0))
    assert np.all(np.asarray(state["scores"]) < -1e8)
    levels, ids = sample(jax.random.key(1), state, 8)
    assert np.all(np.asarray(ids) == -1)  # empty buffer: fresh levels only
    env_levels = generate(jax.random.split(jax.random.key(7), 3))
    # three envs all on fresh levels; mean positive advantages 1.0, 3.0 and 2.0
    adv = jnp.asarray([[1.0, 3.0, -5.0], [1.0, 3.0, 2.0]])
    step_ids = jnp.full((2, 3), -1, jnp.int32)
    env_ids = jnp.asarray([-1, -1, -1], jnp.int32)
    state, new_ids = update(jax.random.key(2), state, Feedback(None, step_ids, adv, env_ids, env_levels,
                                                                   jnp.asarray(0, jnp.int32)))
    np.testing.assert_allclose(state["scores"], [3.0, 1.0])  # env 1 (3.0), then env 0 (1.0; env 2 ties)
    assert np.asarray(new_ids).tolist()[1] == 0
    np.testing.assert_array_equal(gravity_tag(state["levels"])[0], gravity_tag(env_levels)[1])
    # now env 0 plays slot 0 with a low score, which drops the slot below the slot-1 level
    step_ids = jnp.asarray([[0, -2, -2], [0, -2, -2]], jnp.int32)
    adv = jnp.asarray([[0.5, 0.0, 0.0], [0.5, 0.0, 0.0]])
    state2, ids2 = update(jax.random.key(3), state, Feedback(None, step_ids, adv,
                                                                 jnp.asarray([0, 1, -2], jnp.int32), env_levels,
                                                                 jnp.asarray(1, jnp.int32)))
    np.testing.assert_allclose(state2["scores"], [1.0, 0.5])
    assert np.asarray(ids2).tolist() == [1, 0, -2]  # slot 0 moved to 1 and slot 1 to 0
    levels, ids = sample(jax.random.key(4), state2, 200)
    counts = np.bincount(np.asarray(ids), minlength=2)
    assert counts[0] > counts[1] > 0  # rank prioritised
