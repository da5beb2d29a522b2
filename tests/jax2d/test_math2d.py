"""Small helpers of the solver: index reads and writes for loop indices."""

import jax
import jax.numpy as jnp
import numpy as np

import jax2d
from jax2d.math2d import at, set_at, take_rows


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


def test_take_rows_gathers_each_scenes_own_rows():
    """Per-scene indices (n, B) into a batch-last array pick each scene's entries from that scene only,
    along any axis, and out-of-range indices take the fill value."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(7, 3, 4)).astype(np.float32)  # (N, mid, B)
    idx = rng.integers(0, 7, size=(5, 4)).astype(np.int32)
    want = np.stack([x[idx[:, s], :, s] for s in range(4)], axis=-1)  # (5, 3, 4)
    np.testing.assert_array_equal(np.asarray(take_rows(jnp.asarray(x), jnp.asarray(idx))), want)
    y = np.moveaxis(x, 0, 1)  # (mid, N, B): the axis next to the batch
    np.testing.assert_array_equal(np.asarray(take_rows(jnp.asarray(y), jnp.asarray(idx), axis=1)),
                                  np.moveaxis(want, 0, 1))
    idx[0, 2] = 7  # past the end
    got = np.asarray(take_rows(jnp.asarray(x), jnp.asarray(idx), fill=0))
    assert np.all(got[0, :, 2] == 0) and np.array_equal(got[1:], want[1:])
    np.testing.assert_array_equal(np.asarray(take_rows(jnp.asarray(x), jnp.asarray(idx[:, 0]), fill=0))[1:],
                                  x[idx[1:, 0]])
