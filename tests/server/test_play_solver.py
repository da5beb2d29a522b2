"""The server picks the solver per level: the walls-grouping one where polygon slots 0-3 are static walls."""

from __future__ import annotations

import numpy as np
import pytest

from jax2d import SolverConfig
from kinetix.level import WALLS_SOLVER, empty_level, solver_for, walls_static
from kinetix.levels import load_level
from server.play import steps
from tests.server.conftest import LEVELS

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def no_walls_document() -> dict:
    """Our format allows this: a fixed floor in polygon slot 0 and a moving triangle in slot 1 (no standard walls)."""
    return {
        "format_version": 1,
        "bodies": [
            {"shape": "polygon", "position": [2.5, 0.5], "vertices": [[-2, -0.5], [2, -0.5], [2, 0.5], [-2, 0.5]],
             "fixed": True},
            {"shape": "polygon", "position": [2.5, 1.6], "vertices": [[-0.5, -0.5], [0.5, -0.5], [0, 0.5]]},
        ],
    }


def test_solver_for_uses_the_walls_solver_only_when_slots_0_to_3_are_static() -> None:
    walls = load_level(LEVELS / "car_right.json").level
    plain = load_level(no_walls_document()).level
    assert walls_static(empty_level("s")) and walls_static(walls) and not walls_static(plain)
    assert solver_for(walls) == WALLS_SOLVER and WALLS_SOLVER.num_static == 4
    assert solver_for(plain) == SolverConfig() and solver_for([walls, plain]) == SolverConfig()
    assert solver_for([empty_level("l"), empty_level("l")]) == WALLS_SOLVER


def test_a_level_without_walls_gets_its_own_stepper_and_its_body_in_slot_1_still_lands_on_the_floor() -> None:
    """With num_static=4 the pair (slot 0, slot 1) would never be checked and the triangle would fall through."""
    file = load_level(no_walls_document())
    stepper = steps.stepper_for(file)
    assert stepper.env.config.solver == SolverConfig()
    walls_file = load_level(LEVELS / "car_right.json")
    assert steps.stepper_for(walls_file).env.config.solver == WALLS_SOLVER
    state, params = stepper.start(file)
    for _ in range(90):  # 3 s at frame skip 2
        state, _ = stepper.step(state, steps.action_from_keys(set()), params)
    y = float(np.asarray(state.level.sim.bodies.position)[1, 1])
    assert 1.0 < y < 1.5, f"the triangle should rest on the floor (top at y = 1.0), its centre is at y = {y:.3f}"
