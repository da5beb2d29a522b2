"""GAE with hand-computed numbers: truncation bootstraps from the successor's value, termination does not."""

import jax.numpy as jnp
import numpy as np

from kinetix.agents.ppo import compute_gae

REWARD = jnp.asarray([[0.0], [0.0], [1.0]])
VALUE = jnp.asarray([[1.0], [2.0], [3.0]])
BOOTSTRAP = jnp.asarray([[2.0], [5.0], [7.0]])  # V(s') per step; at step 1 the last observation before a reset
DONE = jnp.asarray([[0.0], [1.0], [0.0]])


def test_truncated_step_bootstraps_from_its_final_observation():
    # gamma 0.5, lambda 1: delta = (0 + .5*2 - 1, 0 + .5*5 - 2, 1 + .5*7 - 3) = (0, 0.5, 1.5)
    # A2 = 1.5; A1 = 0.5 (the episode ended: no chaining into step 2); A0 = 0 + 0.5 * A1 = 0.25
    adv, ret = compute_gae(REWARD, VALUE, BOOTSTRAP, jnp.zeros_like(DONE), DONE, gamma=0.5, lam=1.0)
    np.testing.assert_allclose(np.asarray(adv)[:, 0], [0.25, 0.5, 1.5])
    np.testing.assert_allclose(np.asarray(ret)[:, 0], [1.25, 2.5, 4.5])


def test_terminated_step_does_not_bootstrap():
    # step 1 terminated: delta1 = 0 - 2 = -2, so A1 = -2 and A0 = 0 + 0.5 * -2 = -1
    adv, _ = compute_gae(REWARD, VALUE, BOOTSTRAP, DONE, DONE, gamma=0.5, lam=1.0)
    np.testing.assert_allclose(np.asarray(adv)[:, 0], [-1.0, -2.0, 1.5])


def test_lambda_discounts_the_chain():
    # no episode end, gamma 0.5, lambda 0.5: A2 = 1.5, A1 = 0.5 + .25 * 1.5 = 0.875, A0 = 0 + .25 * 0.875
    zeros = jnp.zeros_like(DONE)
    adv, _ = compute_gae(REWARD, VALUE, BOOTSTRAP, zeros, zeros, gamma=0.5, lam=0.5)
    np.testing.assert_allclose(np.asarray(adv)[:, 0], [0.21875, 0.875, 1.5])
