"""Heavy-on-light stacks on the levels' standard walls sink at most two slops (issue 35, "Mass ratios").

tests/jax2d/test_mass_ratio.py's stacks, standing in the middle of a level's floor (kinetix.level.add_walls), with
the physics parameters every level gets (LevelParams().sim_params()), under both solvers the env uses: the walls
solver (kinetix.level.WALLS_SOLVER, the walls' pairs grouped into few colours) and the plain SolverConfig()
(EnvConfig's default). Before the stiffening of loaded contacts the 100:1 stacks reached 14.4 mm here.
"""

from __future__ import annotations

import functools

import pytest

import jax2d
from kinetix import level
from tests.jax2d import mass_ratio
from tests.jax2d.test_mass_ratio import SECONDS, SPECS, check

SOLVERS = {"walls solver": level.WALLS_SOLVER, "plain solver": jax2d.SolverConfig()}


def add_walls(state: jax2d.SimState):
    """mass_ratio.build's floor: the four standard walls; the column stands in the middle of the floor."""
    floor = 0  # kinetix.level.WALLS: polygon 0 is the floor, its top at y = 0.4
    return level.add_walls(state), floor, (2.5, 0.4)


@functools.cache
def _results(solver: str) -> tuple[dict, ...]:
    return tuple(mass_ratio.measure(SPECS, SECONDS, level.LevelParams().sim_params(), SOLVERS[solver], add_walls,
                                    checkpoints=(5.0,)))


@pytest.mark.parametrize("solver", SOLVERS)
@pytest.mark.parametrize("index", range(len(SPECS)), ids=[s.label for s in SPECS])
def test_a_heavy_on_light_stack_on_the_level_floor_sinks_at_most_two_slops(index, solver):
    check(SPECS[index], _results(solver)[index])
