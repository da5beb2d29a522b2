"""The sweeps' schedules: which contact colours and joint slots a step visits."""

import jax.numpy as jnp
import numpy as np

from jax2d import joint_solver, sweeps
from jax2d.sweeps import CONST_ROWS


def test_contact_schedule_lists_colours_with_a_point_in_any_scene_in_order():
    C, K, B = 6, 3, 4
    const = np.zeros((C, len(CONST_ROWS), K, B), np.float32)
    const[5, CONST_ROWS.index("nmass1"), 2, 3] = 0.5  # colour 5: point 1 of one slot, in the last scene only
    const[2, CONST_ROWS.index("nmass0"), 0, 0] = 1.0
    const[4, CONST_ROWS.index("tmass0"), 0, 0] = 1.0  # a tangent mass alone is not a point
    plan = sweeps.schedule(jnp.asarray(const))
    assert int(plan.count) == 2
    assert np.asarray(plan.order)[:2].tolist() == [2, 5]
    assert sorted(np.asarray(plan.order).tolist()) == list(range(C))


def test_joint_schedule_lists_slots_active_in_any_scene_in_order():
    J, B = 5, 3
    zeros = jnp.zeros((J, B))
    revolute = zeros.at[3, 1].set(1.0)
    weld = zeros.at[0, 2].set(1.0)
    jc = joint_solver.JointConstraints(*([zeros] * len(joint_solver.JointConstraints._fields)))
    jc = jc._replace(revolute=revolute, weld=weld)
    plan = joint_solver.schedule(jc)
    assert int(plan.count) == 2
    assert np.asarray(plan.order)[:2].tolist() == [0, 3]
