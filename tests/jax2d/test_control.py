"""SolverConfig.control_flow (jax2d/control.py): skipped work (the default) or fixed loop counts.

The CI machine has no GPU: these lower the step for "cuda" without one to see what a GPU would get, and step
both ways on the CPU to see that they compute the same.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from tests.jax2d import scenes
from tests.jax2d.test_backends import _lowered_text
from tests.jax2d.test_physics import PARAMS, random_actions, small_random_scenes


def _conditionals(stablehlo: str) -> int:
    return stablehlo.count("stablehlo.case") + stablehlo.count("stablehlo.if")


def test_fixed_control_flow_has_no_conditionals_and_skip_is_the_default():
    """Fixed: no conditional in the step (every stage runs, every loop has a static count), for any platform;
    skip, the default everywhere, keeps its skips."""
    config = jax2d.SolverConfig()
    assert config.control_flow == "skip"
    fixed = jax2d.SolverConfig(control_flow="fixed")
    assert _conditionals(_lowered_text("cuda", 8, fixed)) == 0
    assert _conditionals(_lowered_text("cpu", 8, fixed)) == 0
    assert _conditionals(_lowered_text("cpu", 8, config)) > 10


_step = jax2d.jit(lambda states, motors, thrusts, config: jax2d.step_batch(states, PARAMS, motors, thrusts,
                                                                           config=config),
                  static_argnames="config")


def test_fixed_and_skip_compute_the_same_steps():
    """24 random scenes (joints, thrusters, contacts, static walls), 10 steps, each step started from the skip
    state both ways: a difference is one step's rounding (the fixed loops visit empty colours and inactive joint
    slots, which change nothing, but XLA fuses the two programs differently)."""
    batch, steps = 24, 10
    motors, thrusts = random_actions(np.random.default_rng(5), steps, (batch,))
    states = start = scenes.stack(small_random_scenes(batch))
    skip = jax2d.SolverConfig(control_flow="skip")
    fixed = jax2d.SolverConfig(control_flow="fixed")
    worst = 0.0
    for t in range(steps):
        m, th = jnp.asarray(motors[t]), jnp.asarray(thrusts[t])
        a, b = _step(states, m, th, config=skip), _step(states, m, th, config=fixed)
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
            x, y = np.asarray(x), np.asarray(y)
            if x.dtype.kind != "f":
                np.testing.assert_array_equal(x, y)
            else:
                worst = max(worst, float(np.max(np.abs(x - y) / (1.0 + np.abs(x)), initial=0.0)))
        states = a
    assert np.max(np.abs(np.asarray(states.bodies.position) - np.asarray(start.bodies.position))) > 1e-3
    assert worst < 1e-5, worst


def test_an_unknown_control_flow_is_refused():
    with pytest.raises(ValueError, match="control_flow must be one of skip, fixed"):
        jax2d.SolverConfig(control_flow="graph")
    assert dataclasses.replace(jax2d.SolverConfig(), control_flow="fixed").control_flow == "fixed"
