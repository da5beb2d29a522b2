"""The size classes, xl included (issue 28): names agree everywhere, an xl level round-trips, the env steps it."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from jax2d import scene
from kinetix import cli
from kinetix.actions import sample_random_action
from kinetix.env import EnvConfig, make_env
from kinetix.generate import sample_level
from kinetix.level import (
    ROLE_GREEN,
    SIZES,
    LevelFile,
    LevelParams,
    empty_level,
    make_level,
    size_class,
    size_for_counts,
    solver_for,
)
from kinetix.levels import dumps, load_level


def test_the_cli_lists_the_same_size_classes_as_the_levels():
    assert cli.SIZES == tuple(SIZES)


def test_xl_holds_more_than_l_and_counts_beyond_l_pick_it():
    xl, big = size_class("xl"), size_class("l")
    assert (xl.polygons, xl.circles, xl.joints, xl.thrusters) == (64, 16, 24, 8)
    assert size_for_counts(13, 4, 6, 2) == xl and size_for_counts(12, 4, 6, 2) == big
    assert size_for_counts(65, 1, 1, 1).name == "custom"


def xl_level():
    """An xl level past l in every count: 30 boxes in rows, 10 balls, 8 welded box pairs, 3 thrusters."""
    sim = empty_level("xl").sim
    boxes = []
    for k in range(30):
        sim, box = scene.add_rectangle(sim, (0.4 + 0.3 * (k % 15), 0.6 + 0.5 * (k // 15)), 0.2, 0.2)
        boxes.append(box)
    balls = []
    for k in range(10):
        sim, ball = scene.add_circle(sim, (0.5 + 0.4 * k, 2.5), 0.1)
        balls.append(ball)
    for k in range(8):
        a, b = boxes[2 * k], boxes[2 * k + 1]
        position = np.asarray(sim.bodies.position)
        sim, _ = scene.add_fixed_joint(sim, a, b, tuple((position[a] + position[b]) / 2))
    for k in range(3):
        sim, _ = scene.add_thruster(sim, boxes[20 + k], tuple(np.asarray(sim.bodies.position)[boxes[20 + k]]),
                                    angle=np.pi / 2, power=0.5)
    roles = np.zeros(sim.num_bodies, np.int32)
    roles[balls[0]] = ROLE_GREEN
    return LevelFile(make_level(sim, roles=roles), LevelParams(), size_class("xl"))


def test_an_xl_level_round_trips_through_our_format():
    file = xl_level()
    text = dumps(file)
    assert json.loads(text)["size"] == "xl"
    again = load_level(json.loads(text))
    assert again.size == size_class("xl")
    assert dumps(again) == text
    np.testing.assert_array_equal(np.asarray(again.level.sim.bodies.position),
                                  np.asarray(file.level.sim.bodies.position))


@pytest.mark.slow
def test_the_env_steps_an_xl_level_with_random_actions():
    file = xl_level()
    env = make_env(EnvConfig("xl", solver=solver_for(file.level)), file)
    obs, state = env.reset(jax.random.key(0))
    start = np.asarray(state.level.sim.bodies.position)
    transition = jax2d.jit(env.transition)
    for i in range(20):
        state, *_ = transition(state, sample_random_action(jax.random.key(i), env.config.action))
    obs = env.observe(state)
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(obs))
    position = np.asarray(state.level.sim.bodies.position)
    assert np.all(np.isfinite(position))
    ball = file.level.sim.num_polygons
    assert position[ball, 1] < start[ball, 1] - 0.1  # the first ball fell


@pytest.mark.slow
def test_the_generator_makes_xl_levels_that_load_back():
    level = sample_level(jax.random.key(3), "xl")
    assert level.sim.num_polygons == 64 and level.sim.num_circles == 16
    file = load_level(json.loads(dumps(LevelFile(level, LevelParams(), size_class("xl")))))
    assert file.size == size_class("xl")
    active = np.asarray(file.level.sim.bodies.active)
    assert active.sum() > 4  # more than the walls
