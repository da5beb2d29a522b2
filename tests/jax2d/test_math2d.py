"""Small helpers of the solver: index reads and writes for loop indices."""

import jax
import jax.numpy as jnp
import numpy as np

import jax2d
from jax2d.math2d import at, set_at


def test_at_and_set_at_match_indexing_inside_a_loop() -> None:
    x = jnp.arange(24.0).reshape(4, 3, 2)

    @jax2d.jit
    def sweep(x):
        def body(i, carry):
            total, y = carry
            return total + at(x, i), set_at(y, i, at(x, i) * 2.0)

        return jax.lax.fori_loop(0, x.shape[0], body, (jnp.zeros((3, 2)), jnp.zeros_like(x)))

    total, doubled = sweep(x)
    np.testing.assert_array_equal(total, np.asarray(x).sum(axis=0))
    np.testing.assert_array_equal(doubled, 2.0 * np.asarray(x))
