"""Issue 28's accuracy scenes (tests/jax2d/accuracy.py builds and measures them; `python -m
tests.jax2d.accuracy` prints every figure). Printed numbers show with `pytest -s`."""

from __future__ import annotations

import numpy as np

from tests.jax2d import accuracy


def test_newtons_cradle_keeps_its_energy_and_passes_the_impact_to_the_last_ball():
    result = accuracy.cradle()
    print(f"\n[cradle] energy after / before {result['energy_ratio']:.4f}, velocities {result['velocities']}")
    assert abs(result["energy_ratio"] - 1.0) < 0.02
    np.testing.assert_allclose(result["velocities"], [0.0, 0.0, 3.0], atol=0.05)
    assert result["frozen"] == 0
