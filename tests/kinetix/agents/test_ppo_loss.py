"""The clipped PPO loss's drift diagnostics on hand-set probability ratios: approx_kl = mean((r - 1) - log r) and
clip_frac = share of |r - 1| > clip_eps, both 0 when the policy has not moved."""

import math

import jax
import jax.numpy as jnp
import numpy as np

from kinetix.agents import distributions
from kinetix.agents.ppo import TrainConfig, Transition, make_network, ppo_loss
from kinetix.env import EnvConfig, make_env
from kinetix.level import empty_level

SAMPLES = 8


def _batch_and_current_log_prob():
    """A batch of SAMPLES states of an empty s level, random actions, and their log-probabilities under fresh
    parameters: the policy that 'collected' the batch, before any update."""
    config = TrainConfig(width=16, hidden=32)
    env = make_env(EnvConfig("s"), empty_level("s"))
    obs, _ = env.reset(jax.random.key(0))
    batch_obs = jax.tree.map(lambda x: jnp.stack([x] * SAMPLES), obs)
    actions = jnp.stack([env.action_space.sample(jax.random.key(i)) for i in range(SAMPLES)])
    network = make_network(config, "multi_discrete")
    params = network.init(jax.random.key(1), batch_obs)["params"]
    outputs, _ = network.apply({"params": params}, batch_obs)
    log_prob = distributions.log_prob(outputs, actions, "multi_discrete")
    zeros = jnp.zeros(SAMPLES)
    batch = Transition(batch_obs, actions, log_prob, zeros, zeros, zeros, zeros, zeros)
    return config, network, params, batch


def _drift(config, network, params, batch):
    zeros = jnp.zeros(SAMPLES)
    _, aux = ppo_loss(network, "multi_discrete", config, params, batch, zeros, zeros)
    return float(aux["approx_kl"]), float(aux["clip_frac"])


def test_an_unmoved_policy_reads_zero_drift():
    config, network, params, batch = _batch_and_current_log_prob()
    kl, clipped = _drift(config, network, params, batch)
    assert abs(kl) < 1e-6 and clipped == 0.0


def test_drift_matches_the_ratios_set_by_hand():
    config, network, params, batch = _batch_and_current_log_prob()
    # half the samples had log-probability 0.5 lower when collected: ratio e^0.5 = 1.65, outside 1 +- 0.2;
    # a quarter 0.1 higher: ratio e^-0.1 = 0.905, inside; the rest unchanged
    shift = jnp.asarray([0.5] * 4 + [-0.1] * 2 + [0.0] * 2)
    moved = Transition(batch.obs, batch.action, batch.log_prob - shift, *[jnp.zeros(SAMPLES)] * 5)
    kl, clipped = _drift(config, network, params, moved)
    expected = sum(math.expm1(d) - d for d in np.asarray(shift)) / SAMPLES
    np.testing.assert_allclose(kl, expected, rtol=1e-4)
    assert clipped == 0.5
