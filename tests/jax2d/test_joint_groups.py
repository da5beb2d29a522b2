"""narrow_phase.joint_connected: which bodies a chain of joints links (the pair filter's "jointed")."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from jax2d.narrow_phase import joint_connected, joint_labels
from jax2d.state import Joints


def _joints(a, b, active) -> Joints:
    J = len(a)
    zeros = jnp.zeros((J,))
    return Joints(a=jnp.asarray(a, jnp.int32), b=jnp.asarray(b, jnp.int32), anchor_a=jnp.zeros((J, 2)),
                  anchor_b=jnp.zeros((J, 2)), ref_angle=zeros, active=jnp.asarray(active, bool),
                  fixed=jnp.zeros((J,), bool), motor_on=jnp.zeros((J,), bool), motor_speed=zeros,
                  motor_power=zeros, limit_on=jnp.zeros((J,), bool), lower=zeros, upper=zeros,
                  impulse=jnp.zeros((J, 6)))


def _closure_by_search(a, b, active, M) -> np.ndarray:
    """The reference: a depth-first search from every body over the active joints."""
    neighbours = {i: set() for i in range(M)}
    for x, y, on in zip(a, b, active, strict=True):
        if on:
            neighbours[x].add(y)
            neighbours[y].add(x)
    reach = np.zeros((M, M), bool)
    for start in range(M):
        seen, todo = {start}, [start]
        while todo:
            for n in neighbours[todo.pop()] - seen:
                seen.add(n)
                todo.append(n)
        reach[start, sorted(seen)] = True
    return reach


@pytest.mark.parametrize("M,J", [(7, 1), (9, 2), (16, 6), (80, 24)])  # the s, m, l and xl size classes
def test_joint_groups_equal_a_graph_search_on_random_joint_lists(M, J):
    rng = np.random.default_rng(M)
    connected = jax2d.jit(jax.vmap(lambda j: joint_connected(j, M)))
    cases = []
    for _ in range(40):
        a, b = rng.integers(0, M, J), rng.integers(0, M, J)
        if rng.random() < 0.3:  # one long chain, in a shuffled slot order: the case that needs every round
            order = rng.permutation(M)[: J + 1]
            links = rng.permutation(J)
            a, b = order[links], order[links + 1]
        cases.append((a, b, rng.random(J) < 0.8))
    batch = jax.tree.map(lambda *x: jnp.stack(x), *(_joints(*c) for c in cases))
    got = np.asarray(connected(batch))
    for k, (a, b, active) in enumerate(cases):
        np.testing.assert_array_equal(got[k], _closure_by_search(a, b, active, M), err_msg=f"case {k}")


def test_a_chain_in_reverse_slot_order_links_its_two_ends():
    """Joint k links bodies J - k and J - k - 1 (slot 0 at the chain's far end): the smallest label starts at
    the last slot and must travel through all J joints."""
    J = 24
    chain = _joints(list(range(J, 0, -1)), list(range(J - 1, -1, -1)), [True] * J)
    labels = np.asarray(joint_labels(chain, J + 5))
    assert (labels[: J + 1] == 0).all() and labels[J + 1:].tolist() == list(range(J + 1, J + 5))
    broken = _joints(list(range(J, 0, -1)), list(range(J - 1, -1, -1)), [k != 10 for k in range(J)])
    reach = np.asarray(joint_connected(broken, J + 5))
    assert reach[0, J - 10 - 1] and not reach[0, J] and reach[J, J - 10]
