"""kinetix.devices: one CPU device per core, and physics batches split over them.

Runs in a subprocess: XLA reads the device count once, when JAX starts.
"""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = textwrap.dedent("""
    import json
    from kinetix.devices import request_cpu_devices
    request_cpu_devices(2)  # before JAX starts, as the CLI does
    import jax
    import jax2d
    import jax.numpy as jnp
    import numpy as np
    from kinetix.jaxcache import enable_compilation_cache
    enable_compilation_cache()
    from jax2d import SimParams, step
    from kinetix.bench import scenes
    from kinetix.devices import batch_devices, per_device, shard_batch

    batch, steps = 6, 30
    states = scenes.build_batch("s", batch, seed=3)
    rng = np.random.default_rng(0)
    motor = jnp.asarray(rng.uniform(-1, 1, (steps, batch, states.num_joints)), jnp.float32)
    thrust = jnp.asarray(rng.uniform(0, 1, (steps, batch, states.num_thrusters)), jnp.float32)
    vstep = jax.vmap(lambda s, m, t: step(s, SimParams(), m, t, config=scenes.CONFIG))

    def rollout(states, motor, thrust):
        return jax.lax.scan(lambda s, a: (vstep(s, *a), None), states, (motor, thrust))[0]

    single = jax2d.jit(rollout)(states, motor, thrust)
    # As the benches and PPO split a batch: each device steps its own scenes (per_device).
    split = jax2d.jit(per_device(rollout, batch, in_axes=(0, 1, 1)))(
        shard_batch(states, batch), *shard_batch((motor, thrust), batch, axis=1))
    # Each device runs the program a one-device run of its half of the batch runs: bitwise the same.
    half = batch // 2
    halves = [jax2d.jit(rollout)(jax.tree.map(lambda x: x[i:i + half], states), motor[:, i:i + half],
                                 thrust[:, i:i + half]) for i in (0, half)]
    by_halves = jax.tree.map(lambda a, b: np.concatenate([a, b]), *halves)
    print(json.dumps({
        "same_as_halves": all(np.array_equal(np.asarray(a), np.asarray(b))
                              for a, b in zip(jax.tree.leaves(by_halves), jax.tree.leaves(split))),
        "device_count": jax.device_count(),
        "devices_for_6": batch_devices(6), "devices_for_5": batch_devices(5),
        "split_over": len(split.bodies.position.sharding.device_set),
        "moved": float(np.abs(np.asarray(single.bodies.position) - np.asarray(states.bodies.position)).max()),
        "max_difference": max(float(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)).max())
                              for a, b in zip(jax.tree.leaves(single), jax.tree.leaves(split))),
        # per leaf: difference within 2e-4 of the leaf's largest magnitude (plus 5e-5)
        "close": all(float(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)).max(initial=0.0))
                     <= 5e-5 + 2e-4 * float(np.abs(np.asarray(a, np.float64)).max(initial=0.0))
                     for a, b in zip(jax.tree.leaves(single), jax.tree.leaves(split))),
    }))
""")


@pytest.mark.slow  # a fresh process compiling for two devices
def test_batch_split_over_two_cpu_devices_equals_one_device():
    env = {key: value for key, value in os.environ.items() if key != "XLA_FLAGS"}
    env.update(JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, cwd=ROOT,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["device_count"] == 2  # request_cpu_devices took effect
    assert (result["devices_for_6"], result["devices_for_5"]) == (2, 1)  # an odd batch stays on one device
    assert result["split_over"] == 2  # the batch really ran on both
    assert result["moved"] > 1e-3  # the scenes are not at rest
    assert result["same_as_halves"]  # each device steps its scenes exactly as one device steps them alone
    # Against the whole batch on one device: the same per-scene solver, but XLA compiles the 6-scene and the
    # 3-scene programs apart and rounds differently (the first step differs by 2e-9). After 30 steps of
    # contact the trajectories agree to that rounding grown by the contacts (measured: 4.9e-4 rad/s on
    # angular velocities up to 5.4 rad/s, 2e-5 m on separations), not bitwise.
    assert result["close"], result["max_difference"]
    assert result["max_difference"] <= 1e-3


CONFINE_SCRIPT = textwrap.dedent("""
    import json, os
    from kinetix.devices import confine_to_one_core, usable_cores
    confined = confine_to_one_core()  # before JAX starts, as the benches' loop child does
    import jax
    import jax2d
    import jax.numpy as jnp
    total = float(jax2d.jit(lambda x: (x * 2).sum())(jnp.arange(1000.0)))  # JAX's backend and threads running
    threads = os.listdir("/proc/self/task")
    print(json.dumps({"confined": confined, "cores": usable_cores(), "total": total, "threads": len(threads),
                      "thread_cores": sorted({len(os.sched_getaffinity(int(t))) for t in threads})}))
""")


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="this OS has no CPU affinity")
def test_confine_to_one_core_holds_for_every_thread_jax_starts():
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "-c", CONFINE_SCRIPT], capture_output=True, text=True, env=env, cwd=ROOT,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["confined"] is True and result["cores"] == 1
    assert result["total"] == 999000.0
    assert result["threads"] > 1  # XLA started threads of its own ...
    assert result["thread_cores"] == [1]  # ... and every one of them runs on the one core


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="this OS has no CPU affinity")
def test_confine_to_one_core_rejects_a_core_the_process_may_not_use():
    from kinetix.devices import confine_to_one_core

    with pytest.raises(ValueError, match="core 100000 is not available"):
        confine_to_one_core(100000)
