"""Which bodies touch: the pair table and the touching matrix against the contact slots they are read from."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from jax2d.pairs import contact_layout
from jax2d.touching import TOUCH_TOLERANCE, pair_slots, touching_matrix

CAPACITIES = [(5, 2), (6, 3), (12, 4), (4, 0), (8, 2), (12, 12)]


@pytest.mark.parametrize("capacity", CAPACITIES)
def test_pair_slots_names_each_pairs_own_slot(capacity) -> None:
    P, C = capacity
    N = P + C
    layout = contact_layout(P, C)
    table = pair_slots(P, C)
    S = len(layout.slot_a)
    assert table.shape == (N, N)
    np.testing.assert_array_equal(np.diag(table), S)
    np.testing.assert_array_equal(table, table.T)
    for i in range(N):
        for j in range(N):
            if i != j:
                s = table[i, j]
                assert {int(layout.slot_a[s]), int(layout.slot_b[s])} == {i, j}


@pytest.mark.parametrize("capacity", [(5, 2), (12, 4)])
def test_touching_matrix_is_the_slots_with_a_close_point(capacity) -> None:
    """Random contact flags and separations: a pair touches when one of its slot's active points is within the
    tolerance, whichever way round the pair is named."""
    P, C = capacity
    state = jax2d.empty_state(jax2d.Capacity(polygons=P, circles=C, joints=1, thrusters=1))
    layout = contact_layout(P, C)
    rng = np.random.default_rng(0)
    S = len(layout.slot_a)
    active = rng.random((S, 2)) < 0.3
    separation = rng.uniform(-0.02, 0.05, (S, 2)).astype(np.float32)
    contacts = dataclasses.replace(state.contacts, active=jnp.asarray(active), separation=jnp.asarray(separation))
    touching = np.asarray(touching_matrix(dataclasses.replace(state, contacts=contacts)))
    N = P + C
    expected = np.zeros((N, N), bool)
    for s in range(S):
        a, b = int(layout.slot_a[s]), int(layout.slot_b[s])
        if a < N and b < N and np.any(active[s] & (separation[s] <= TOUCH_TOLERANCE)):
            expected[a, b] = expected[b, a] = True
    assert expected.any() and not expected.all()
    np.testing.assert_array_equal(touching, expected)
