"""Heavy-on-light stacks sink at most two slops, into each other and into the floor (issue 35, "Mass ratios").

Every stack of mass_ratio.variations() on the accuracy scene's static slab, stepped 10 s in one batch (one
compile): the largest overlap between neighbouring boxes and with the floor over the whole run, and at 5 and
10 s. The same stacks on the levels' standard walls: tests/kinetix/test_mass_ratio_walls.py. Before the
stiffening of loaded contacts (contact_solver.load_softness) the 100:1 stack of the accuracy scene rested at
8.7 mm and reached 15.4 mm while settling, and 100 on 1 on 1 kg reached 24.6 mm.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

import jax2d
from tests.jax2d import mass_ratio

SECONDS = 10.0
SLOP = jax2d.SimParams().linear_slop
SPECS = mass_ratio.variations()


@functools.cache
def _results() -> tuple[dict, ...]:
    return tuple(mass_ratio.measure(SPECS, SECONDS, checkpoints=(5.0,)))


def check(spec: mass_ratio.Stack, result: dict) -> None:
    """The stack's overlaps stay within 2 slops over the whole run (and so at 5 and 10 s), it stays in place and
    nothing froze."""
    print(f"\n[{spec.label}] end {result['end'] * 1000:.2f} mm, at 5 s {result['at'][0] * 1000:.2f} mm, largest "
          f"{result['sink'] * 1000:.2f} mm (between {np.round(np.array(result['worst_between']) * 1000, 2)}, "
          f"floor {result['worst_floor'] * 1000:.2f}); drift {result['x_drift'] * 1000:.1f} mm")
    assert result["sink"] < 2 * SLOP
    assert result["x_drift"] < 2 * SLOP  # it still stands where it was put
    assert result["frozen"] == 0


@pytest.mark.parametrize("index", range(len(SPECS)), ids=[s.label for s in SPECS])
def test_a_heavy_on_light_stack_sinks_at_most_two_slops(index):
    check(SPECS[index], _results()[index])
