"""`kinetix bench env`: environment throughput, latency, compile times and pixel-renderer cost.

What is measured, per level (one per size class by default):
- batched rollout (training): B copies of the environment under vmap, `steps` agent steps inside one
  jitted lax.scan, with symbolic-entity observations, uniformly random multi-discrete actions and
  auto-reset, stepped with the solver the level allows (kinetix.level.solver_for, see _make_env);
  steps_per_s = B * steps / seconds of one run (the median of 5 when short, see bench.engine.timed_runs),
  excluding compilation; the batch is split over the CPU devices (`--devices`, default one per core)
  when they divide it, each device stepping its own environments (kinetix.devices.per_device);
- Python loop (the interactive path): one env step per call at batch 1, blocking on each result, with
  state and params packed in one buffer each (`env.step_compact`), and the plain pytree `env.step`,
  timed in a child process with one device on one core (kinetix.bench.engine.interactive_loops);
- cold compile seconds of one jitted `env.step` and one jitted `env.reset` at batch 1;
- the JAX pixel renderer: ms per frame at batch 1 from a Python loop and per frame inside a vmapped batch,
  at the pixel-observation resolution and at 256 px, with its cold compile seconds.

The default levels are the three public Kinetix files the reference numbers were measured on, read from
../shared beside the checkout; without it, project levels of the same size classes stand in.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import sys
import time
from pathlib import Path

from kinetix.bench.engine import (
    COMPILE_LOOP_CALLS,
    LOOP_CALLS,
    LOOP_WARMUP,
    SEED,
    all_finite,
    backend_flag,
    cold_compiles,
    machine_row,
    machine_summary,
    measured_on,
    run_with_interactive_loops,
    timed_runs,
)

REPO_DIR = Path(__file__).resolve().parents[2]
SHARED_LEVELS = REPO_DIR.parent / "shared" / "kinetix-levels"
# The files of the reference table (kinetix-env 3.0.2 on this machine kind).
REFERENCE_LEVELS = {"s": "s/h2_one_wheel_car.json", "m": "m/h5_angry_birds.json", "l": "l/h4_cartpole.json"}
# Stand-ins of the same size classes from levels/ when ../shared is absent.
PROJECT_LEVELS = {"s": "unicycle.json", "m": "car_right.json", "l": "cartpole.json"}
PIXEL_RESOLUTIONS = (64, 256)
PIXEL_BATCH = 64


def default_level_paths(sizes: list[str]) -> list[Path]:
    """The reference level of each size class, or the project's stand-in when ../shared is missing."""
    paths = []
    for size in sizes:
        shared = SHARED_LEVELS / REFERENCE_LEVELS[size]
        paths.append(shared if shared.is_file() else REPO_DIR / "levels" / PROJECT_LEVELS[size])
    return paths


def _make_env(level_file, control_flow: str | None = None):
    """The bench's environment of `level_file` and its params; control_flow: the solver's (SolverConfig), if not
    the level's own ("auto")."""
    import dataclasses

    from kinetix.env import EnvConfig, EnvParams, make_env
    from kinetix.level import solver_for

    # The solver every caller that knows its levels picks (the server, `kinetix train`, `kinetix bench engine
    # --level`), and what the public Kinetix's env does by default (num_static_fixated_polys=4): the walls one
    # when polygon slots 0-3 are static (env s 16: 9.4k -> 12.1-12.7k steps/s; docs/engine.md, issue 35).
    solver = solver_for(level_file.level)
    if control_flow is not None:
        solver = dataclasses.replace(solver, control_flow=control_flow)
    config = EnvConfig(size=level_file.size, observation="entity", action="multi_discrete",
                       frame_skip=level_file.params.frame_skip, solver=solver)
    return make_env(config, level_file), EnvParams.from_level_params(level_file.params)


def measure_rollout(level_file, name: str, batch: int, steps: int, cold: bool = True) -> dict:
    """Agent steps per second of `batch` environments stepped `steps` times in one jitted scan."""
    from kinetix.devices import batch_devices

    run, compile_s, setup_s = compile_rollout(level_file, batch, steps, cold)
    seconds, result, runs = timed_runs(run)
    states, _, episodes_ended = result
    return {
        "what": "env",
        "size": level_file.size.name,
        "level": name,
        "batch": batch,
        "steps": steps,
        "steps_per_s": batch * steps / seconds,
        "seconds": seconds,
        "runs": runs,
        "compile_s": compile_s,
        "setup_s": setup_s,
        "devices": batch_devices(batch),
        "episodes_ended": int(episodes_ended.sum()),
        "finite": all_finite(states),
        **measured_on(),
    }


def compile_rollout(level_file, batch: int, steps: int, cold: bool = True, control_flow: str | None = None):
    """(run, compile seconds, set-up seconds): `run()` steps `batch` environments `steps` times in one jitted scan
    (auto-reset, random multi-discrete actions) and returns (states, summed rewards, episodes ended) per
    environment, asynchronously (block on it to time it)."""
    import jax
    import jax.numpy as jnp

    import jax2d
    from kinetix.actions import sample_random_action
    from kinetix.devices import per_device, shard_batch

    env, params = _make_env(level_file, control_flow)
    action_type = env.config.action

    # Every environment carries its own key, and each device steps its own environments
    # (kinetix.devices.per_device): nothing is exchanged between devices inside the scan.
    @functools.partial(per_device, batch=batch, in_axes=(0, None))
    def rollout(keys, params):
        _, states = jax.vmap(env.reset, in_axes=(0, None))(keys, params)

        def one_env_step(key, state, params):
            key, act_key, step_key = jax.random.split(key, 3)
            action = sample_random_action(act_key, action_type)
            obs, state, reward, terminated, truncated, info = env.step(step_key, state, action, params)
            return key, state, reward, terminated | truncated

        def one_step(carry, _):
            keys, states, rewards, ends = carry
            keys, states, reward, ended = jax.vmap(one_env_step, in_axes=(0, 0, None))(keys, states, params)
            return (keys, states, rewards + reward, ends + ended), None

        zeros = jnp.zeros(keys.shape[0], jnp.float32)
        (_, states, rewards, ends), _ = jax.lax.scan(one_step, (keys, states, zeros, zeros.astype(jnp.int32)),
                                                     None, length=steps)
        return states, rewards, ends  # per environment

    start = time.perf_counter()  # set-up: the keys; the environments are reset on the device, inside the rollout
    keys = jax.block_until_ready(shard_batch(jax.random.split(jax.random.PRNGKey(SEED), batch), batch))
    setup_s = time.perf_counter() - start
    if cold:
        jax.clear_caches()
    start = time.perf_counter()
    compiled = jax2d.jit(rollout).lower(keys, params).compile()
    compile_s = time.perf_counter() - start
    return (lambda: compiled(keys, params)), compile_s, setup_s


def measure_python_loop(level_file, name: str, calls: int = LOOP_CALLS, cold: bool = True) -> dict:
    """Mean ms per env step at batch 1 from Python, and cold compile seconds of step and reset.

    latency_ms is the packed loop (`env.step_compact`: one buffer in and out, see jax2d.compact),
    pytree_latency_ms the plain `env.step` on pytrees; step_compile_s and reset_compile_s are the
    plain `env.step` / `env.reset`, compact_compile_s the packed step.
    """
    import jax
    import numpy as np

    import jax2d
    from jax2d.compact import pack, unpack_host
    from kinetix.actions import sample_random_action
    from kinetix.devices import usable_cores

    env, params = _make_env(level_file)
    total = LOOP_WARMUP + calls
    actions = np.asarray(jax.vmap(lambda k: sample_random_action(k, env.config.action))(
        jax.random.split(jax.random.PRNGKey(SEED), total)))
    # Numpy rows, like the actions: indexing a JAX array would add a dispatch of its own to every call.
    keys = np.asarray(jax.random.split(jax.random.PRNGKey(SEED + 1), total))

    if cold:
        jax.clear_caches()
    reset, step = jax2d.jit(env.reset), jax2d.jit(env.step)
    start = time.perf_counter()
    obs, state = jax.block_until_ready(reset(keys[0], params))
    reset_compile_s = time.perf_counter() - start
    start = time.perf_counter()
    out = jax.block_until_ready(step(keys[0], state, actions[0], params))
    step_compile_s = time.perf_counter() - start

    def loop(step, carried, params, carry) -> tuple[float, object]:
        """Time the calls; `carry(output)` is what the next call takes."""
        for i in range(1, LOOP_WARMUP):
            carried = carry(jax.block_until_ready(step(keys[i], carried, actions[i], params)))
        start = time.perf_counter()
        for i in range(LOOP_WARMUP, total):
            carried = carry(jax.block_until_ready(step(keys[i], carried, actions[i], params)))
        return 1000.0 * (time.perf_counter() - start) / calls, carried

    pytree_ms, state = loop(step, out[1], params, carry=lambda output: output[1])
    finite = all_finite(state)

    # The packed loop (env.step_compact), the way a Python loop at batch 1 should call the env.
    if cold:
        jax.clear_caches()
    packed_params = jax2d.jit(pack)(params)
    reset_compact, step_compact = jax2d.jit(env.reset_compact), jax2d.jit(env.step_compact)
    packed = jax.block_until_ready(reset_compact(keys[0], packed_params))
    start = time.perf_counter()
    packed = jax.block_until_ready(step_compact(keys[0], packed, actions[0], packed_params))
    compact_compile_s = time.perf_counter() - start
    latency_ms, packed = loop(step_compact, packed, packed_params, carry=lambda output: output)
    return {
        "what": "env",
        "size": level_file.size.name,
        "level": name,
        "batch": 1,
        "mode": "python_loop",
        "calls": calls,
        "latency_ms": latency_ms,
        "pytree_latency_ms": pytree_ms,
        "compile_s": step_compile_s,
        "step_compile_s": step_compile_s,
        "reset_compile_s": reset_compile_s,
        "compact_compile_s": compact_compile_s,
        "devices": jax.device_count(),
        "cores": usable_cores(),
        "finite": finite and all_finite(unpack_host(packed).state),
        **measured_on(),
    }


def measure_renderer(level_file, name: str, resolution: int, calls: int = 100, cold: bool = True) -> dict:
    """The JAX pixel renderer: ms per frame at batch 1 (Python loop) and inside a vmapped batch."""
    import jax
    import jax.numpy as jnp

    import jax2d
    from kinetix.render import render_pixels

    level = level_file.level
    single = jax2d.jit(lambda lv: render_pixels(lv, resolution))
    batched = jax2d.jit(jax.vmap(lambda lv: render_pixels(lv, resolution)))
    stack = jax.tree.map(lambda x: jnp.stack([x] * PIXEL_BATCH), level)

    if cold:
        jax.clear_caches()
    start = time.perf_counter()
    jax.block_until_ready(single(level))
    compile_s = time.perf_counter() - start
    for _ in range(5):
        jax.block_until_ready(single(level))
    start = time.perf_counter()
    for _ in range(calls):
        jax.block_until_ready(single(level))
    loop_ms = 1000.0 * (time.perf_counter() - start) / calls

    jax.block_until_ready(batched(stack))
    start = time.perf_counter()
    repeats = 3
    for _ in range(repeats):
        jax.block_until_ready(batched(stack))
    batched_ms = 1000.0 * (time.perf_counter() - start) / (repeats * PIXEL_BATCH)
    return {
        "what": "env",
        "size": level_file.size.name,
        "level": name,
        "mode": "pixels",
        "resolution": resolution,
        "ms_per_frame": loop_ms,
        "ms_per_frame_batched": batched_ms,
        "render_batch": PIXEL_BATCH,
        "compile_s": compile_s,
    }


def benchmark(level_files: list, batches: list[int], steps: int, *, loop_calls: int = LOOP_CALLS,
              pixel_resolutions=PIXEL_RESOLUTIONS, report=lambda result: None, cold: bool = True,
              loops: bool = True) -> list[dict]:
    """Measure each (name, LevelFile) at every batch size, its Python-loop latency and the renderer.

    Results go to `report` as they are measured and are returned in order, ending with a peak-RSS line.
    """
    results = []

    def record(result: dict) -> None:
        results.append(result)
        report(result)

    with cold_compiles() if cold else contextlib.nullcontext():
        for name, level_file in level_files:
            for batch in batches:
                record(measure_rollout(level_file, name, batch, steps, cold))
            if loops:
                record(measure_python_loop(level_file, name, loop_calls, cold))
            for resolution in pixel_resolutions:
                record(measure_renderer(level_file, name, resolution, cold=cold))
    record(machine_summary("env", compile_cache="disabled" if cold else "allowed"))
    return results


# ---------------------------------------------------------------- output

_HEADER = f"{'size':<5}{'level':<24}{'batch':>6}  {'mode':<12}{'steps/s':>12}{'ms/call':>10}{'compile s':>11}"


def table_row(result: dict) -> str:
    """One line of the readable table for a result of `benchmark`."""
    if "peak_rss_mb" in result:
        return machine_row(result)
    head = f"{result['size']:<5}{result['level'][:23]:<24}"
    if result.get("mode") == "pixels":
        return (f"{head}{'':>6}  {'pixels ' + str(result['resolution']):<12}{'':>12}{result['ms_per_frame']:>10.3f}"
                f"{result['compile_s']:>11.2f}  ({result['ms_per_frame_batched']:.3f} ms/frame in a batch of "
                f"{result['render_batch']})")
    warning = "" if result["finite"] else "  NON-FINITE STATE"
    if result.get("mode") == "python_loop":
        pytree = f"; pytree env.step {result['pytree_latency_ms']:.3f} ms" if "pytree_latency_ms" in result else ""
        return (f"{head}{1:>6}  {'python loop':<12}{'':>12}{result['latency_ms']:>10.3f}"
                f"{result['step_compile_s']:>11.2f}  (reset compile {result['reset_compile_s']:.2f} s{pytree})"
                f"{warning}")
    ms_per_call = 1000.0 * result["batch"] / result["steps_per_s"]
    devices = f"  ({result['devices']} devices)" if result.get("devices", 1) > 1 else ""
    return (f"{head}{result['batch']:>6}  {'scan':<12}{result['steps_per_s']:>12,.0f}{ms_per_call:>10.3f}"
            f"{result['compile_s']:>11.2f}{devices}{warning}")


def load_bench_levels(args: argparse.Namespace) -> list[tuple[str, object, Path]] | None:
    """(name, LevelFile, path) of --level or of the reference level of each of --sizes; None (after printing why)
    when one does not load."""
    from kinetix.level import LevelError
    from kinetix.levels import load_level

    paths = [Path(args.level)] if args.level else default_level_paths(args.sizes)
    levels = []
    for path in paths:
        try:
            levels.append((path.stem, load_level(path), path))
        except LevelError as error:
            print(f"cannot load level {path}: {error}", file=sys.stderr)
            return None
    return levels


def run(args: argparse.Namespace) -> int:
    loaded = load_bench_levels(args)
    if loaded is None:
        return 2
    level_files = [(name, level_file) for name, level_file, _ in loaded]

    if args.json:
        def report(result: dict) -> None:
            print(json.dumps(result), flush=True)
    else:
        print(f"kinetix env, {args.steps} agent steps per rollout (symbolic-entity observations, random "
              "multi-discrete actions, auto-reset); compile times are cold")
        print("python loop: one env, env.step_compact per call, in a child process on one core; "
              "its compile times are this process's")
        print(_HEADER, flush=True)

        def report(result: dict) -> None:
            print(table_row(result), flush=True)

    loop_only = getattr(args, "loop_only", False)
    if loop_only:
        results = benchmark(level_files, [], args.steps, report=report, pixel_resolutions=())
    else:  # the loops' latencies come from a one-device, one-core child (interactive_loops)
        results = run_with_interactive_loops(
            functools.partial(benchmark, level_files, args.batches, args.steps, loop_calls=COMPILE_LOOP_CALLS), "env",
            (["--level", args.level] if args.level else ["--sizes", ",".join(args.sizes)]) + backend_flag(args),
            report)
    return 0 if all(result.get("finite", True) for result in results) else 1
