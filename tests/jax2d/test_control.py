"""SolverConfig.control_flow (jax2d/control.py): skipped work on the CPU, fixed loop counts elsewhere.

The CI machine has no GPU: these lower the step for "cuda" without one to see what a GPU gets, and step both
ways on the CPU to see that they compute the same. tests/test_gpu.py runs the step on a GPU where there is one.
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


def test_lowered_for_a_gpu_the_step_has_no_conditionals(monkeypatch):
    """Lowered for CUDA the step reads no predicate back to the host: every stage runs and every loop has a
    static count; lowered for the CPU it keeps its skips. The default config, "auto", decides by the platform.
    In a process whose only backend is a GPU there is no conditional at all; with several backends (a GPU
    machine also has its CPU) only lax.platform_dependent's choice, a case on a constant that XLA folds."""
    config = jax2d.SolverConfig()
    assert config.control_flow == "auto"
    monkeypatch.setattr(jax2d.compiling, "only_platform", lambda: "cuda")
    assert _conditionals(_lowered_text("cuda", 8, config)) == 0
    monkeypatch.setattr(jax2d.compiling, "only_platform", lambda: None)
    cuda = _lowered_text("cuda", 8, config)
    assert _conditionals(cuda) == 2 and '"stablehlo.case"(%c' in cuda  # the platform index: a constant
    assert _conditionals(_lowered_text("cpu", 8, config)) > 10


def test_on_a_cpu_only_machine_auto_is_the_skip_program():
    """A CPU-only process compiles exactly the program it did before control_flow existed: "auto" is "skip"."""
    states = scenes.stack(small_random_scenes(8))
    m = jnp.zeros((8, states.num_joints), jnp.float32)
    th = jnp.zeros((8, states.num_thrusters), jnp.float32)

    def program(control_flow: str) -> str:  # without source locations: "auto" reaches the step by another path
        config = jax2d.SolverConfig(control_flow=control_flow)
        return jax2d.jit(lambda s, m, th: jax2d.step_batch(s, PARAMS, m, th, config=config)).lower(
            states, m, th).as_text(debug_info=False)

    auto = program("auto")
    assert len(auto) > 100_000 and auto == program("skip")
    assert auto != program("fixed")


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
    with pytest.raises(ValueError, match="control_flow must be one of auto, skip, fixed"):
        jax2d.SolverConfig(control_flow="graph")
    assert dataclasses.replace(jax2d.SolverConfig(), control_flow="fixed").control_flow == "fixed"
