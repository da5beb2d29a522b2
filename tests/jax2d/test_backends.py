"""What jax2d does per backend: the CPU's batch split (SolverConfig.chunk) and its compile options.

The CI machine has no GPU; these check on the CPU what the GPU gets (by lowering for "cuda" without one) and
that the CPU's split changes nothing but rounding. tests/test_gpu.py runs the step on a GPU where there is one.
"""

import functools
import re

import jax
import jax.numpy as jnp
import numpy as np

import jax2d
from tests.jax2d import scenes
from tests.jax2d.test_physics import PARAMS, random_actions, small_random_scenes

WHOLE = jax2d.SolverConfig(chunk=1 << 30)


@functools.partial(jax2d.jit, static_argnames="config")
def _one_step(states, motors, thrusts, config):
    return jax2d.step_batch(states, PARAMS, motors, thrusts, config=config)


def test_forty_scenes_in_parts_of_ten_equal_one_pass_on_the_cpu():
    """40 random scenes, 12 steps: chunk=10 (4 interleaved parts, one after the other on the CPU) against the
    whole batch at once (the GPU's way). Each step starts both from the one-pass state, so a difference is one
    step's rounding (XLA may contract multiply-adds differently for batch widths 10 and 40), not its growth."""
    worst = stepwise_gap(WHOLE, jax2d.SolverConfig(chunk=10), batch=40, steps=12, seed=24)
    assert worst < 1e-5, worst


def stepwise_gap(first: jax2d.SolverConfig, second: jax2d.SolverConfig, batch: int, steps: int, seed: int) -> float:
    """The largest gap, relative to 1 + |value|, between one step under `first` and one under `second`, each
    step taken from the same state (first's trajectory) on random scenes with random actions; integer leaves
    must be equal. Asserts that the scenes moved."""
    motors, thrusts = random_actions(np.random.default_rng(seed), steps, (batch,))
    states = start = scenes.stack(small_random_scenes(batch))
    worst = 0.0
    for t in range(steps):
        m, th = jnp.asarray(motors[t]), jnp.asarray(thrusts[t])
        a, b = _one_step(states, m, th, first), _one_step(states, m, th, second)
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
            x, y = np.asarray(x), np.asarray(y)
            if x.dtype.kind != "f":
                np.testing.assert_array_equal(x, y)
            else:
                worst = max(worst, float(np.max(np.abs(x - y) / (1.0 + np.abs(x)), initial=0.0)))
        states = a
    moved = np.max(np.abs(np.asarray(states.bodies.position) - np.asarray(start.bodies.position)))
    assert moved > 1e-3  # the scenes did something
    return worst


def test_with_one_backend_the_split_is_decided_when_tracing(monkeypatch):
    """A CPU-only process splits without tracing the GPU's way (no platform conditional in the program); a
    process whose only backend is a GPU steps the batch whole."""
    config = jax2d.SolverConfig(chunk=4)
    bodies = small_random_scenes(1)[0].bodies.position.shape[0]
    part = f"tensor<4x{bodies}x2xf32>"
    # Lowered for CUDA, yet split: the decision was the CPU-only process's, made while tracing.
    assert part in _lowered_text("cuda", 12, config)
    monkeypatch.setattr(jax2d.compiling, "only_platform", lambda: "cuda")
    assert part not in _lowered_text("cpu", 12, config)


def _lowered_text(platform: str, batch: int, config: jax2d.SolverConfig) -> str:
    """The StableHLO of one batched step lowered for `platform` (no device of that platform is needed)."""
    states = scenes.stack(small_random_scenes(batch))
    m = jnp.zeros((batch, states.num_joints), jnp.float32)
    th = jnp.zeros((batch, states.num_thrusters), jnp.float32)
    step = jax.jit(lambda s, m, th: jax2d.step_batch(s, PARAMS, m, th, config=config))  # noqa: TID251 - export
    return jax.export.export(step, platforms=[platform])(states, m, th).mlir_module()


def test_the_batch_is_split_on_the_cpu_only(monkeypatch):
    """chunk=4 at batch 12: lowered for the CPU the step runs on parts of 4 scenes (lax.map: one loop more);
    lowered for CUDA (any platform but the CPU) it runs the 12 scenes at once and no part appears.
    As on a machine with a GPU (several backends), where the lowering platform decides."""
    monkeypatch.setattr(jax2d.compiling, "only_platform", lambda: None)
    config = jax2d.SolverConfig(chunk=4)
    bodies = small_random_scenes(1)[0].bodies.position.shape[0]
    part, whole = f"tensor<4x{bodies}x2xf32>", f"tensor<12x{bodies}x2xf32>"
    cpu, cuda = _lowered_text("cpu", 12, config), _lowered_text("cuda", 12, config)
    assert part in cpu and whole in cpu
    assert part not in cuda and whole in cuda
    assert cpu.count("stablehlo.while") == cuda.count("stablehlo.while") + 1


def test_a_batch_no_larger_than_chunk_lowers_the_same_everywhere(monkeypatch):
    """Below the chunk nothing is platform dependent: the program is the same for every platform."""
    monkeypatch.setattr(jax2d.compiling, "only_platform", lambda: None)
    def scrub(text: str) -> str:  # without source locations and the platform's name
        text = "\n".join(line for line in text.splitlines() if not line.startswith("#loc"))
        return re.sub(r"mhlo\.platforms = \[[^\]]*\]|\s*loc\(#loc\d*\)", "", text)

    config = jax2d.SolverConfig(chunk=8)
    assert scrub(_lowered_text("cpu", 8, config)) == scrub(_lowered_text("cuda", 8, config))
