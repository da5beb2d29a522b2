"""jax2d.jit: jax.jit with the engine's XLA options, and the same physics as plain jax.jit."""

import jax
import numpy as np
import pytest

import jax2d
from jax2d import compiling
from tests.jax2d import scenes


def test_jit_passes_the_engine_options_and_lets_the_caller_add_or_override(monkeypatch) -> None:
    seen = []
    monkeypatch.setattr(compiling.jax, "jit", lambda fun, **kwargs: seen.append(kwargs) or fun)
    jax2d.jit(len, static_argnames="x")
    jax2d.jit(len, compiler_options={"xla_cpu_use_fusion_emitters": True, "xla_cpu_enable_fast_math": False})
    # Each call jits twice: with the options for calls from Python, without them for nested calls.
    assert seen[:2] == [{"compiler_options": jax2d.COMPILER_OPTIONS, "static_argnames": "x"}, {"static_argnames": "x"}]
    assert seen[2]["compiler_options"] == {"xla_cpu_use_fusion_emitters": True, "xla_cpu_enable_fast_math": False}
    assert jax2d.COMPILER_OPTIONS == {"xla_cpu_use_fusion_emitters": False}  # the caller's dict did not leak in


def test_an_unknown_option_reaches_xla_and_is_refused() -> None:
    with pytest.raises(Exception, match="no_such_option"):
        jax2d.jit(lambda x: x + 1, compiler_options={"xla_no_such_option": True})(np.float32(1))


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


@pytest.mark.parametrize("seed", [3, 11])
def test_engine_options_give_the_same_physics_as_plain_jit(seed: int) -> None:
    """Other kernels, same arithmetic: a crowded jointed scene under random motor and thruster actions
    agrees with plain jax.jit over 60 steps to float32 rounding, which the contacts amplify
    (measured: bitwise equal for seed 3, 1.6e-4 m apart for seed 11)."""
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
    np.testing.assert_allclose(ours, plain, atol=1e-3)
