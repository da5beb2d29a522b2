"""The sharded path (env batch split over 2 CPU devices) and the single-device path give the same update.

Runs in a subprocess: XLA_FLAGS=--xla_force_host_platform_device_count=2 must be set before JAX starts.
"""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]

SCRIPT = textwrap.dedent("""
    import json
    import jax
    import jax2d
    import numpy as np
    from kinetix.jaxcache import enable_compilation_cache
    enable_compilation_cache()
    from kinetix.agents import curricula
    from kinetix.agents.ppo import TrainConfig, make_train
    from kinetix.agents.sharding import batch_sharder, local_mesh
    from kinetix.env import EnvConfig, EnvParams, make_env
    from kinetix.generate import sample_level

    assert jax.local_device_count() == 2, jax.devices()
    generator = lambda key: sample_level(key, "s")
    env = make_env(EnvConfig("s"), generator)
    config = TrainConfig(num_envs=4, num_steps=8, num_minibatches=2, update_epochs=2, width=16, hidden=32,
                         total_timesteps=64)
    params = EnvParams(max_timesteps=6)  # short episodes, so auto-reset happens inside the rollout
    results = {}
    for name, shard in (("single", None), ("sharded", batch_sharder(local_mesh(), config.num_envs))):
        trainer = make_train(config, env, params, curricula.domain_randomisation(generator), shard=shard)
        runner = jax2d.jit(trainer.init)(jax.random.key(0))
        runner, metrics = jax2d.jit(trainer.update)(runner)
        devices = len(runner.env_state.timestep.sharding.device_set)
        leaves = [np.asarray(x).tolist() for x in jax.tree.leaves(runner.train_state.params)]
        results[name] = {"devices": devices, "params": leaves, "episodes": float(metrics["episodes"]),
                         "value_loss": float(metrics["value_loss"])}
    print(json.dumps(results))
""")


def _on_two_devices(script: str) -> dict:
    """The JSON object `script` prints last, run in a fresh process with two CPU devices."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu",
               PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, cwd=ROOT,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # a fresh process compiling for two devices: about a minute on an idle 2-core machine
def test_sharded_update_equals_single_device_update():
    results = _on_two_devices(SCRIPT)
    single, sharded = results["single"], results["sharded"]
    assert single["devices"] == 1 and sharded["devices"] == 2  # the env batch really was split
    assert single["episodes"] == sharded["episodes"] > 0
    import numpy as np

    np.testing.assert_allclose(sharded["value_loss"], single["value_loss"], rtol=1e-4, atol=1e-6)
    for a, b in zip(single["params"], sharded["params"], strict=True):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-4, atol=1e-6)


SCORING = textwrap.dedent("""
    import json
    import jax
    import jax2d
    import numpy as np
    from kinetix.jaxcache import enable_compilation_cache
    enable_compilation_cache()
    from kinetix.agents.ppo import TrainConfig, make_network
    from kinetix.agents.sharding import batch_sharder, local_mesh
    from kinetix.agents.train import sfl_scorer
    from kinetix.env import EnvConfig, EnvParams, make_env
    from kinetix.generate import sample_level

    assert jax.local_device_count() == 2, jax.devices()
    env = make_env(EnvConfig("s"), lambda key: sample_level(key, "s"))
    params = EnvParams(max_timesteps=8)
    network = make_network(TrainConfig(width=16, hidden=32), "multi_discrete")
    obs, _ = env.reset(jax.random.key(0))
    net_params = network.init(jax.random.key(1), jax.tree.map(lambda x: x[None], obs))["params"]
    mesh = local_mesh()
    results = {}
    for name, place_rows in (("single", lambda rows: None), ("sharded", lambda rows: batch_sharder(mesh, rows))):
        score = sfl_scorer(env, params, lambda: network, place_rows)

        @jax2d.jit
        def scored(key, net_params):
            levels = jax.vmap(env.reset_fn)(jax.random.split(key, 6))
            return score(key, net_params, levels, 4)

        p = scored(jax.random.key(2), net_params)
        results[name] = {"devices": len(p.sharding.device_set), "p": np.asarray(p).tolist()}
    print(json.dumps(results))
""")


@pytest.mark.slow  # a fresh process compiling for two devices
def test_sfl_scoring_splits_its_episodes_over_the_devices():
    """SFL's candidates come from replicated keys: unless placed, every device plays every scoring episode."""
    results = _on_two_devices(SCORING)
    assert results["single"]["devices"] == 1 and results["sharded"]["devices"] == 2
    assert results["sharded"]["p"] == results["single"]["p"] and len(results["single"]["p"]) == 6
