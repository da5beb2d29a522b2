"""jax2d.jit: jax.jit with the engine's XLA options, and the same physics as plain jax.jit."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from jax2d import compiling
from tests.jax2d import scenes

CPU_OPTIONS = {"xla_cpu_use_fusion_emitters": False,
               "xla_cpu_experimental_ynn_fusion_type": compiling.CPU_LIBRARY_FUSIONS}
GPU_OPTIONS = {"xla_gpu_enable_command_buffer": compiling.GPU_COMMAND_BUFFERS,
               "xla_gpu_command_buffer_scheduling_mode": "CONCURRENT"}


def test_an_option_the_compiler_refuses_is_left_out_with_a_warning() -> None:
    """XLA's options change between versions (jax 0.11's CPU compiler refuses xla_cpu_use_fusion_emitters):
    a refused one is dropped, once, with a warning, and the function still compiles and runs."""
    with pytest.warns(UserWarning, match="cpu compiles without xla_cpu_no_such_option_for_this_test"):
        twice = jax2d.jit(lambda x: 2 * x, compiler_options={"xla_cpu_no_such_option_for_this_test": True})
        assert float(twice(jnp.float32(3))) == 6.0
    probes = len(compiling._PROBED)
    refused = {"xla_cpu_no_such_option_for_this_test": True}
    assert compiling.accepted_options("cpu", {**refused, **CPU_OPTIONS}) == CPU_OPTIONS
    assert compiling.accepted_options("cpu", CPU_OPTIONS) == CPU_OPTIONS
    assert len(compiling._PROBED) <= probes + 1  # each option is probed once per process, accepted or not


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="YNNPACK library calls are the CPU compiler's")
def test_on_the_cpu_only_matrix_products_become_library_calls() -> None:
    """CPU_LIBRARY_FUSIONS: a layer's product stays a YNNPACK call, a short reduction is XLA's own loop (by
    default both are library calls, and the step's ~50 reductions cost env m 256 about 10 %)."""
    def layer_and_sums(w, x):
        return jnp.tanh(x @ w), jnp.min(x.reshape(512, 8, 8), axis=-1), jnp.sum(jnp.abs(x), axis=-1)

    args = (jnp.ones((64, 32)), jnp.ones((512, 64)))
    compiled = jax2d.jit(layer_and_sums).lower(*args).compile()
    engine = compiled.as_text()
    plain = jax.jit(layer_and_sums).lower(*args).compile().as_text()  # noqa: TID251 - XLA's defaults
    assert plain.count("__ynn_fusion") >= 2  # the product and at least one reduction (what the option removes)
    assert engine.count("__ynn_fusion") == 1 and "dot(" in engine
    np.testing.assert_allclose(compiled(*args)[2], 64.0)


def test_jit_passes_the_engine_options_and_lets_the_caller_add_or_override(monkeypatch) -> None:
    seen = []
    monkeypatch.setattr(compiling.jax, "jit", lambda fun, **kwargs: seen.append(kwargs) or fun)
    monkeypatch.setattr(compiling, "only_platform", lambda: "cpu")
    plain = jax2d.jit(len, static_argnames="x")
    assert seen == [{"static_argnames": "x"}]  # the nested version, made at once
    plain("ab")  # the CPU's top-level version, made on the first call from Python
    assert seen[1] == {"compiler_options": CPU_OPTIONS, "static_argnames": "x"}
    jax2d.jit(len, compiler_options={"xla_cpu_use_fusion_emitters": True, "xla_cpu_enable_fast_math": False})("ab")
    assert seen[3]["compiler_options"] == {**CPU_OPTIONS, "xla_cpu_use_fusion_emitters": True,
                                           "xla_cpu_enable_fast_math": False}
    assert jax2d.COMPILER_OPTIONS == {**CPU_OPTIONS, **GPU_OPTIONS}  # the caller's dict did not leak in


def test_the_environment_replaces_or_removes_options_and_the_caller_still_wins(monkeypatch) -> None:
    seen = []
    monkeypatch.setattr(compiling.jax, "jit", lambda fun, **kwargs: seen.append(kwargs) or fun)
    monkeypatch.setattr(compiling, "only_platform", lambda: "cpu")
    monkeypatch.setenv(compiling.OPTIONS_VARIABLE,
                       '{"xla_cpu_use_fusion_emitters": true, "xla_cpu_experimental_ynn_fusion_type": null}')
    jax2d.jit(len)("ab")
    expected = {**CPU_OPTIONS, "xla_cpu_use_fusion_emitters": True}
    del expected["xla_cpu_experimental_ynn_fusion_type"]  # null: XLA's default (or XLA_FLAGS') again
    assert seen[1]["compiler_options"] == expected
    jax2d.jit(len, compiler_options={"xla_cpu_use_fusion_emitters": False})("ab")
    assert seen[3]["compiler_options"]["xla_cpu_use_fusion_emitters"] is False
    monkeypatch.setenv(compiling.OPTIONS_VARIABLE, " ")
    assert compiling.environment_options() == {}


@pytest.mark.parametrize("value", ["xla_gpu_enable_command_buffer=", "[1, 2]", '{"a": 1'])
def test_a_malformed_environment_override_is_a_clear_error(monkeypatch, value: str) -> None:
    monkeypatch.setenv(compiling.OPTIONS_VARIABLE, value)
    with pytest.raises(ValueError, match="JAX2D_COMPILER_OPTIONS .*object"):
        jax2d.jit(len)


@pytest.mark.parametrize("platform", ["gpu", "cuda", "rocm", "tpu", "GPU"])
def test_no_cpu_option_reaches_another_platform(platform: str) -> None:
    """XLA refuses an option its backend lacks: every CUDA compile failed on xla_cpu_use_fusion_emitters."""
    assert compiling.options_for("cpu", jax2d.COMPILER_OPTIONS) == CPU_OPTIONS
    assert compiling.options_for(platform, jax2d.COMPILER_OPTIONS) == ({} if platform == "tpu" else GPU_OPTIONS)
    mixed = {"xla_cpu_enable_fast_math": False, "xla_gpu_autotune_level": 0, "xla_tpu_x": 1, "xla_llvm_y": 2}
    kept = compiling.options_for(platform, mixed)
    assert not any(name.startswith("xla_cpu_") for name in kept) and kept["xla_llvm_y"] == 2
    assert ("xla_gpu_autotune_level" in kept) == (platform.lower() != "tpu")
    assert ("xla_tpu_x" in kept) == (platform == "tpu")
    assert compiling.options_for("cpu", mixed) == {"xla_cpu_enable_fast_math": False, "xla_llvm_y": 2}


def test_a_call_on_a_gpu_compiles_without_the_cpu_options(monkeypatch) -> None:
    """Where a process has several backends, each call's platform picks its own top-level jit."""
    seen = []
    monkeypatch.setattr(compiling.jax, "jit", lambda fun, **kwargs: seen.append(kwargs) or fun)
    monkeypatch.setattr(compiling, "only_platform", lambda: None)  # as on a machine with a GPU
    monkeypatch.setattr(compiling, "call_platform", lambda leaves, fixed=None: "gpu")
    jitted = jax2d.jit(len)
    jitted("ab")
    assert seen[1] == {"compiler_options": GPU_OPTIONS}  # no GPU here: the probe cannot refuse it
    monkeypatch.setattr(compiling, "call_platform", lambda leaves, fixed=None: "cpu")
    jitted("ab")
    assert seen[2] == {"compiler_options": CPU_OPTIONS}
    jitted("abc")  # each platform's version is made once
    assert len(seen) == 3


def test_the_call_platform_follows_jax_placement_rules() -> None:
    """Committed arguments first, then the jit's own device or backend, then jax.default_device, then the
    default backend (what JAX itself does with a call)."""
    cpu = jax.devices("cpu")[0]
    loose, committed = jnp.ones(2), jax.device_put(jnp.ones(2), cpu)
    assert not loose.committed and committed.committed
    assert compiling.call_platform([loose, committed], fixed="tpu", default_device="gpu",
                                   default_backend="gpu") == "cpu"
    assert compiling.call_platform([loose, 3], fixed="tpu", default_device="gpu", default_backend="gpu") == "tpu"
    assert compiling.call_platform([loose], default_device="gpu", default_backend="tpu") == "gpu"
    assert compiling.call_platform([loose], default_device=cpu, default_backend="gpu") == "cpu"
    assert compiling.call_platform([loose], default_backend="gpu") == "gpu"
    with jax.default_device(cpu):  # read from JAX's config when not given
        assert compiling.call_platform([loose], default_backend="gpu") == "cpu"
    assert compiling._fixed_platform({"device": cpu}) == "cpu"
    assert compiling._fixed_platform({"backend": "gpu"}) == "gpu"
    sharding = jax.sharding.SingleDeviceSharding(cpu)
    assert compiling._fixed_platform({"in_shardings": (None, sharding)}) == "cpu"
    assert compiling._fixed_platform({"static_argnames": "x"}) is None


def test_a_jitted_step_runs_on_the_cpu_under_a_default_device_and_with_committed_arguments() -> None:
    capacity = jax2d.Capacity(polygons=5, circles=2, joints=2, thrusters=1, max_vertices=4)
    state, _ = scenes.random_scene(2, capacity)
    step = jax2d.jit(jax2d.step)
    motor, thrust = np.zeros(capacity.joints, np.float32), np.zeros(capacity.thrusters, np.float32)
    plain = step(state, jax2d.SimParams(), motor, thrust)
    cpu = jax.devices("cpu")[0]
    with jax.default_device(cpu):
        placed = step(state, jax2d.SimParams(), motor, thrust)
    committed = step(jax.device_put(state, cpu), jax2d.SimParams(), motor, thrust)
    assert committed.bodies.position.committed
    for other in (placed, committed):
        np.testing.assert_array_equal(np.asarray(other.bodies.position), np.asarray(plain.bodies.position))
    assert float(np.max(np.abs(np.asarray(plain.bodies.position) - np.asarray(state.bodies.position)))) > 0


def test_a_jax2d_jit_function_works_inside_other_traces_and_keeps_the_jit_api() -> None:
    """JAX refuses compiler options on a nested jit; jax2d.jit functions must still nest like jax.jit ones."""
    inner = jax2d.jit(lambda x, n: x * n, static_argnames="n")
    outer = jax2d.jit(lambda x: jax.lax.scan(lambda c, _: (inner(c, n=2), None), x, None, length=3)[0])
    assert float(outer(np.float32(1.5))) == 12.0
    assert float(jax.jit(lambda x: inner(x, n=3))(np.float32(2))) == 6.0  # noqa: TID251 - a foreign caller
    assert np.allclose(jax.vmap(lambda x: inner(x, n=2))(np.arange(3.0, dtype=np.float32)), [0, 2, 4])
    assert float(inner.lower(np.float32(1), n=4).compile()(np.float32(1))) == 4.0
    assert inner.__name__ == "<lambda>"
    again = jax2d.jit(inner, static_argnames="n")  # wrapping a Jitted: its attributes must not replace ours
    assert again._top is not inner._top and float(again(np.float32(2), n=5)) == 10.0


@pytest.mark.parametrize("seed,tolerance", [(3, 1e-3), (11, 3e-3)])
def test_engine_options_give_the_same_physics_as_plain_jit(seed: int, tolerance: float) -> None:
    """Other kernels, same arithmetic: a crowded jointed scene under random motor and thruster actions
    agrees with plain jax.jit over 60 steps to float32 rounding, which the contacts amplify
    (measured: bitwise equal for seed 3; for seed 11 1.6e-4 m apart, and 1.4e-3 m for one body since the joint
    solve's sums run in index order (math2d.ordered_sum, 2026-11-26): the two emitters round that chain of adds
    differently and this scene's contacts amplify it)."""
    capacity = jax2d.Capacity(polygons=12, circles=4, joints=6, thrusters=2, max_vertices=8)
    state, _ = scenes.random_scene(seed, capacity)
    rng = np.random.default_rng(seed)
    motor = rng.uniform(-1, 1, (60, capacity.joints)).astype(np.float32)
    thrust = rng.uniform(0, 1, (60, capacity.thrusters)).astype(np.float32)

    def run(jit):
        body = lambda s, a: (jax2d.step(s, jax2d.SimParams(), *a), None)
        return jit(lambda s: jax.lax.scan(body, s, (motor, thrust))[0])(state).bodies.position

    plain = run(jax.jit)  # noqa: TID251 - plain jit is the comparison
    ours = run(jax2d.jit)
    assert np.isfinite(ours).all()
    np.testing.assert_allclose(ours, plain, atol=tolerance)
