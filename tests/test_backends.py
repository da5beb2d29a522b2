"""Choosing the JAX backend (kinetix.devices) and the interactive device, on a machine without a GPU.

tests/test_gpu.py is what runs where there is a GPU.
"""

import json
import subprocess
import sys

import jax
import numpy as np
import pytest

from kinetix import devices
from kinetix.cli import main


def test_on_a_cpu_only_machine_interactive_placement_changes_nothing():
    assert jax.default_backend() == "cpu"
    assert devices.interactive_device() is None
    fn = lambda x: x + 1
    assert devices.on_interactive_device(fn) is fn


def test_where_jax_defaults_to_another_backend_interactive_calls_run_on_the_cpu(monkeypatch):
    """As on a GPU machine: the wrapped call runs under jax.default_device(the CPU) in its own thread only."""
    cpu = jax.devices("cpu")[0]
    monkeypatch.setattr(devices, "interactive_device", lambda: cpu)
    seen = []

    def fn(x):
        seen.append(jax.config.jax_default_device)
        return jax.numpy.asarray(x) * 2

    placed = devices.on_interactive_device(fn)
    assert placed is not fn and placed.__name__ == "fn"
    out = placed(np.float32(3))
    assert seen == [cpu] and float(out) == 6.0 and out.devices() == {cpu} and not out.committed
    assert jax.config.jax_default_device is None  # the context ended with the call


def test_select_backend_refuses_a_gpu_where_there_is_none_and_unknown_names():
    with pytest.raises(devices.BackendError, match=r"no GPU backend.*pip install -e '\.\[cuda\]'"):
        devices.select_backend("gpu")
    with pytest.raises(ValueError, match="unknown backend 'tpu'"):
        devices.select_backend("tpu")
    devices.select_backend(None)
    devices.select_backend("cpu")  # JAX already runs on the CPU: nothing to do
    report = devices.backend_report()
    assert report["backend"] == "cpu" and report["device_kind"] == jax.devices()[0].device_kind
    assert report["jax"] == jax.__version__


def test_bench_with_backend_gpu_fails_clearly_without_a_gpu(capsys):
    argv = ["bench", "engine", "--backend", "gpu", "--devices", "1", "--sizes", "s", "--batches", "1", "--steps", "1"]
    assert main(argv) == 2
    assert "no GPU backend" in capsys.readouterr().err


def test_select_backend_cpu_before_jax_starts_hides_the_other_backends():
    code = ("from kinetix.devices import select_backend; select_backend('cpu'); import jax; "
            "print(jax.config.jax_platforms, jax.default_backend())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    assert out.stdout.split() == ["cpu", "cpu"]


def test_a_level_batch_is_one_broadcast_of_the_scene():
    """`kinetix bench engine --level`: B copies of the level's scene, built as whole arrays on the device."""
    from kinetix.bench.engine import level_workload, rollout_inputs
    from kinetix.levels import load_level

    path = "levels/cartpole.json"
    scene = load_level(path).level.sim
    workload = level_workload(path)
    batch, motor, thrust = rollout_inputs(workload, 5, 3)
    for one, many in zip(jax.tree.leaves(scene), jax.tree.leaves(batch), strict=True):
        assert many.shape == (5, *np.shape(one))
        np.testing.assert_array_equal(np.asarray(many), np.broadcast_to(np.asarray(one), many.shape))
    assert motor.shape == (3, 5, scene.num_joints) and thrust.shape == (3, 5, scene.num_thrusters)
    assert motor.dtype == np.float32 and -1 <= float(motor.min()) < 0 < float(motor.max()) <= 1
    assert 0 <= float(thrust.min()) and float(thrust.max()) <= 1


def test_bench_results_name_their_backend_and_device_kind(capsys):
    from kinetix.bench import engine

    results = engine.benchmark(engine.builtin_workloads(["s"]), [2], 2, cold=False, loops=False)
    rollout, summary = results
    kind = jax.devices()[0].device_kind
    assert (rollout["backend"], rollout["device_kind"]) == ("cpu", kind) and rollout["setup_s"] >= 0
    assert (summary["backend"], summary["device_kind"]) == ("cpu", kind)
    assert f"cpu: {kind}" in engine.table_row(summary)
    json.dumps(results)  # JSON lines stay serialisable
