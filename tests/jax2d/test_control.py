"""SolverConfig.control_flow (jax2d/control.py): skipped work (the default) or fixed loop counts.

The CI machine has no GPU: these lower the step for "cuda" without one to see what a GPU would get, and step
both ways on the CPU to see that they compute the same.
"""

import dataclasses

import pytest

import jax2d
from tests.jax2d.test_backends import _lowered_text, stepwise_gap


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


def test_fixed_and_skip_compute_the_same_steps():
    """24 random scenes (joints, thrusters, contacts), 10 steps, each step started from the skip state both ways:
    a difference is one step's rounding (the fixed loops visit empty colours and inactive joint slots, which
    change nothing, but XLA fuses the two programs differently)."""
    worst = stepwise_gap(jax2d.SolverConfig(control_flow="skip"), jax2d.SolverConfig(control_flow="fixed"),
                         batch=24, steps=10, seed=5)
    assert worst < 1e-5, worst


def test_an_unknown_control_flow_is_refused():
    with pytest.raises(ValueError, match="control_flow must be one of skip, fixed"):
        jax2d.SolverConfig(control_flow="graph")
    assert dataclasses.replace(jax2d.SolverConfig(), control_flow="fixed").control_flow == "fixed"
