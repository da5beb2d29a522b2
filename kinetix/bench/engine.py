"""`kinetix bench engine`: physics throughput and latency of jax2d on the benchmark scenes.

Two ways of running the step are measured, because the project uses both:
- batched rollout (training): B scenes under vmap, `steps` steps inside one jitted lax.scan;
  steps_per_s = B * steps / seconds of one run, excluding compilation (see timed_runs). The batch is
  split over the CPU devices (`--devices`, default one per core; see kinetix.devices) when they divide it,
  each device stepping its own scenes (kinetix.devices.per_device).
- Python loop (interactive): one scene, one jitted step per call, blocking on each result as the server
  does every frame; latency_ms is the mean per call, measured in a child process with one device on one
  core (interactive_loops), and the loop's compile_s in this process (run_with_interactive_loops).

Set-up (setup_s: building the batch and its actions, on the device) is timed apart from the rollout: a batch
is built once and broadcast or indexed as whole arrays, never scene by scene. Every result names the backend
and device kind it ran on (`--backend cpu|gpu` picks one; see kinetix.devices.select_backend).

Compile times are cold: the persistent compilation cache is switched off for the whole benchmark
and JAX's in-memory caches are cleared before each measured compilation. A scan's compile_s is
trace + lower + XLA compile (`jit(...).lower(...).compile()`); the loop's is its first call.

JAX is imported inside the functions, so importing this module (e.g. for `kinetix --help`) stays cheap.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import os
import resource
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

LOOP_CALLS = 500  # timed calls of the single-scene step
# A rollout is timed on its first run after compiling. When that took less than this many seconds it is run
# SHORT_RUNS more times and the median of those is reported: first-run costs (allocation) and the machine's
# noise matter in short runs (0.1 s at B=16, where one run varied by 30 %), and long ones take minutes.
REPEAT_BELOW_S = 2.0
SHORT_RUNS = 5
LOOP_WARMUP = 20  # untimed calls first, so allocation and dispatch caches are warm
SEED = 0
NO_LEVEL_LOADER = "--level needs the level loader (kinetix.levels), which is not built yet"


@dataclass(frozen=True)
class Workload:
    """What to step: a name for the report, a maker of B stacked scenes, the solver config and physics params."""

    name: str
    make_batch: Callable[[int], Any]  # batch size -> SimState with a leading batch axis
    config: Any  # jax2d.SolverConfig
    params: Any = None  # jax2d.SimParams; None for the defaults


def builtin_workloads(sizes: list[str], max_vertices: int = 8) -> list[Workload]:
    from kinetix.bench import scenes

    def maker(size: str) -> Callable[[int], Any]:
        return lambda batch: scenes.build_batch(size, batch, seed=SEED, max_vertices=max_vertices)

    return [Workload(size, maker(size), scenes.CONFIG) for size in sizes]


def level_workload(path: str) -> Workload:
    """The scene of a level file, repeated B times, with the level's physics params.

    Raises ImportError while the level loader (kinetix.levels) does not exist, ValueError for a bad file.
    """
    import jax
    import jax.numpy as jnp

    from kinetix.level import solver_for
    from kinetix.levels import load_level

    file = load_level(path)
    state = file.level.sim

    def make_batch(batch: int):
        # One broadcast per leaf on the device (a Python list of `batch` scenes stacked took 291 s at 2,048).
        return jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x), (batch, *jnp.shape(x))), state)

    # The solver the server plays this level with: the walls one where polygon slots 0-3 are static.
    return Workload(file.name or path, make_batch, solver_for(file.level), file.params.sim_params())


@contextlib.contextmanager
def cold_compiles() -> Iterator[None]:
    """Switch the persistent compilation cache off (and back to its old setting on exit).

    JAX decides once per process whether the cache is in use, at the first compilation; resetting
    the cache makes it look at `jax_enable_compilation_cache` again.
    """
    import jax
    from jax.experimental.compilation_cache import compilation_cache

    was_enabled = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    compilation_cache.reset_cache()
    try:
        yield
    finally:
        jax.config.update("jax_enable_compilation_cache", was_enabled)
        compilation_cache.reset_cache()


def _array_params(params=None):
    """SimParams (default ones if None) as float32 arrays, so calls do not convert Python floats every time."""
    import jax
    import jax.numpy as jnp

    from jax2d import SimParams

    return jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), SimParams() if params is None else params)


def all_finite(state) -> bool:
    """Whether every float in the state is finite (the engine promises never to emit NaN)."""
    import jax
    import numpy as np

    arrays = [np.asarray(leaf) for leaf in jax.tree.leaves(state)]
    return all(bool(np.isfinite(a).all()) for a in arrays if np.issubdtype(a.dtype, np.floating))


def timed_runs(run: Callable[[], Any]) -> tuple[float, Any, int]:
    """(seconds of one run, its result, how many runs were timed) for a compiled, argument-free `run`.

    The first run is reported when it took REPEAT_BELOW_S or more; otherwise it only warms up and the
    median of SHORT_RUNS further runs is reported.
    """
    import jax

    start = time.perf_counter()
    result = jax.block_until_ready(run())
    seconds = time.perf_counter() - start
    if seconds >= REPEAT_BELOW_S:
        return seconds, result, 1
    times = []
    for _ in range(SHORT_RUNS):
        start = time.perf_counter()
        result = jax.block_until_ready(run())
        times.append(time.perf_counter() - start)
    return sorted(times)[len(times) // 2], result, SHORT_RUNS


def rollout_inputs(workload: Workload, batch: int, steps: int) -> tuple:
    """(scenes, motor actions, thruster actions) for a rollout, on the device(s), split as the rollout splits them.

    The actions (motors uniform in [-1, 1], thrusters in [0, 1]) are drawn on the host in float32 and copied once:
    at batch 16,384 and 200 steps they are 20M numbers, which numpy's float64 draw took 1.25 s for and JAX's
    threefry on the CPU device 2-9 s (a loaded 2-core machine).
    """
    import jax
    import numpy as np

    from kinetix.devices import shard_batch

    scenes = shard_batch(workload.make_batch(batch), batch)
    rng = np.random.default_rng(SEED)
    motor = rng.random((steps, batch, scenes.num_joints), dtype=np.float32) * np.float32(2) - np.float32(1)
    thrust = rng.random((steps, batch, scenes.num_thrusters), dtype=np.float32)
    motor, thrust = shard_batch(jax.device_put((motor, thrust)), batch, axis=1)
    return jax.block_until_ready((scenes, motor, thrust))


def compile_rollout(workload: Workload, batch: int, steps: int, cold: bool = True):
    """(run, compile seconds, set-up seconds): `run()` steps `batch` scenes `steps` times inside one jitted scan and
    returns the final scenes, asynchronously (block on it to time it)."""
    import jax

    import jax2d
    from jax2d import step
    from kinetix.devices import per_device

    start = time.perf_counter()
    scenes, motor, thrust = rollout_inputs(workload, batch, steps)
    setup_s = time.perf_counter() - start
    params = _array_params(workload.params)
    step_batch = jax.vmap(lambda s, p, m, t: step(s, p, m, t, config=workload.config), in_axes=(0, None, 0, 0))

    # Actions and params are arguments, not closed-over constants, so they are not baked into the program.
    # Each device steps its own scenes (kinetix.devices.per_device).
    @functools.partial(per_device, batch=batch, in_axes=(0, None, 1, 1))
    def rollout(state, params, motor, thrust):
        return jax.lax.scan(lambda s, a: (step_batch(s, params, *a), None), state, (motor, thrust))[0]

    if cold:
        jax.clear_caches()
    start = time.perf_counter()
    compiled = jax2d.jit(rollout).lower(scenes, params, motor, thrust).compile()
    compile_s = time.perf_counter() - start
    return (lambda: compiled(scenes, params, motor, thrust)), compile_s, setup_s


def measure_rollout(workload: Workload, batch: int, steps: int, cold: bool = True) -> dict:
    """Steps per second of `batch` scenes stepped `steps` times inside one jitted scan, and its cold compile time."""
    from kinetix.devices import batch_devices

    run, compile_s, setup_s = compile_rollout(workload, batch, steps, cold)
    seconds, final, runs = timed_runs(run)
    return {
        "what": "engine",
        "size": workload.name,
        "batch": batch,
        "steps": steps,
        "steps_per_s": batch * steps / seconds,
        "seconds": seconds,
        "runs": runs,
        "compile_s": compile_s,
        "setup_s": setup_s,
        "devices": batch_devices(batch),
        "finite": all_finite(final),
        **measured_on(),
    }


def measure_python_loop(workload: Workload, calls: int = LOOP_CALLS, cold: bool = True) -> dict:
    """Mean milliseconds per call of the jitted single-scene step, blocking on every result, and its compile time.

    Two loops: the packed one (`jax2d.step_compact`: state and params in one buffer each, the way an
    interactive session should hold them) gives latency_ms and compile_s; the plain pytree `jax2d.step`
    gives pytree_latency_ms. Both start from the same state and take the same actions.
    """
    import jax
    import numpy as np

    import jax2d
    from jax2d import step, step_compact
    from jax2d.compact import pack, unpack_host
    from kinetix.devices import usable_cores

    scene = jax.tree.map(lambda x: x[0], workload.make_batch(1))
    rng = np.random.default_rng(SEED)
    total = LOOP_WARMUP + calls
    # Plain numpy rows, as the server receives actions from the browser each frame.
    motor = rng.uniform(-1.0, 1.0, (total, scene.num_joints)).astype(np.float32)
    thrust = rng.uniform(0.0, 1.0, (total, scene.num_thrusters)).astype(np.float32)
    params = _array_params(workload.params)
    config = workload.config

    if cold:
        jax.clear_caches()
    stepper = jax2d.jit(step_compact, static_argnames="config")
    packed, packed_params = jax2d.jit(pack)(scene), jax2d.jit(pack)(params)
    start = time.perf_counter()
    state = jax.block_until_ready(stepper(packed, packed_params, motor[0], thrust[0], config=config))
    compile_s = time.perf_counter() - start

    def loop(stepper, state, params) -> tuple[float, Any]:
        for i in range(1, LOOP_WARMUP):
            state = jax.block_until_ready(stepper(state, params, motor[i], thrust[i], config=config))
        start = time.perf_counter()
        for i in range(LOOP_WARMUP, total):
            state = jax.block_until_ready(stepper(state, params, motor[i], thrust[i], config=config))
        return 1000.0 * (time.perf_counter() - start) / calls, state

    latency_ms, state = loop(stepper, state, packed_params)
    pytree_ms, _ = loop(jax2d.jit(step, static_argnames="config"), scene, params)
    return {
        "what": "engine",
        "size": workload.name,
        "batch": 1,
        "mode": "python_loop",
        "calls": calls,
        "latency_ms": latency_ms,
        "pytree_latency_ms": pytree_ms,
        "compile_s": compile_s,
        "devices": jax.device_count(),
        "cores": usable_cores(),
        "finite": all_finite(unpack_host(state)),
        **measured_on(),
    }


def measured_on() -> dict:
    """The backend and device kind a result was measured on."""
    from kinetix.devices import backend_report

    report = backend_report()
    return {"backend": report["backend"], "device_kind": report["device_kind"]}


def interactive_loops(command: str, selection: list[str]) -> list[dict]:
    """The Python-loop results of `kinetix bench <command> <selection>`, measured in a child process that has
    one device and runs on one core (`kinetix.devices.confine_to_one_core`): the set-up for stepping one scene
    from Python.

    Two XLA CPU devices in the process made a single-scene call 20-25 % slower, and XLA's thread pool
    spreading one scene's tiny kernels over both cores cost another 20-30 % (l: 0.59-0.68 ms against
    0.41-0.48 ms per engine step). The batches, measured in this process, keep both cores.
    """
    from kinetix.devices import DEVICE_COUNT_FLAG

    flags = [flag for flag in os.environ.get("XLA_FLAGS", "").split() if not flag.startswith(DEVICE_COUNT_FLAG)]
    env = {**os.environ, "XLA_FLAGS": " ".join(flags)}
    cmd = [sys.executable, "-m", "kinetix", "bench", command, "--json", "--devices", "1", "--loop-only", *selection]
    child = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    results = [json.loads(line) for line in child.stdout.splitlines() if line.startswith("{")]
    loops = [result for result in results if result.get("mode") == "python_loop"]
    if child.returncode not in (0, 1) or not loops:
        raise RuntimeError(f"the one-device loop measurement failed ({' '.join(cmd)}):\n{child.stderr[-2000:]}")
    return loops


COMPILE_KEYS = ("compile_s", "step_compile_s", "reset_compile_s", "compact_compile_s")
COMPILE_LOOP_CALLS = 10  # the bench process's own loop only times the compiles; the child times the calls


def run_with_interactive_loops(measure: Callable[..., list[dict]], command: str, selection: list[str],
                               report: Callable[[dict], None]) -> list[dict]:
    """`measure(report=..., loops=True)`'s results, with each Python loop's latencies from `interactive_loops`.

    Compile times stay this process's: confined to one core, XLA compiled 1.2-1.9x slower (one step 8.4-9.9 s
    against 5.1-6.8 s for a batch-1 scan in the same runs), and a process that compiles, like the server,
    keeps every core.
    """
    results = measure(report=lambda result: None if result.get("mode") == "python_loop" else report(result),
                      loops=True)
    child = {(result["size"], result.get("level")): result for result in interactive_loops(command, selection)}
    merged = []
    for result in results:
        if result.get("mode") == "python_loop":
            loop = child[(result["size"], result.get("level"))]
            result = {**loop, **{key: result[key] for key in COMPILE_KEYS if key in result},
                      "compile_cores": result["cores"], "finite": loop["finite"] and result["finite"]}
            report(result)
        merged.append(result)
    return merged


def backend_flag(args: argparse.Namespace) -> list[str]:
    """The `--backend` option for the interactive-loop child, so it measures on the same backend."""
    backend = getattr(args, "backend", None)
    return ["--backend", backend] if backend else []


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, in MB (ru_maxrss is KB on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024 * 1024) if sys.platform == "darwin" else peak / 1024


def machine_summary(what: str, **extra) -> dict:
    """The closing result of every bench table: peak memory, device count and the backend, plus `extra`."""
    import jax

    from kinetix.devices import backend_report

    return {"what": what, "peak_rss_mb": peak_rss_mb(), "devices": jax.device_count(), **backend_report(), **extra}


def machine_row(result: dict) -> str:
    """The readable line for a machine_summary result."""
    return (f"peak RSS {result['peak_rss_mb']:.0f} MB (jax {result['jax']}, {result['backend']}: "
            f"{result.get('device_kind', '?')}, {result['devices']} devices)")


def benchmark(
    workloads: list[Workload],
    batches: list[int],
    steps: int,
    *,
    loop_calls: int = LOOP_CALLS,
    report: Callable[[dict], None] = lambda result: None,
    cold: bool = True,
    loops: bool = True,
) -> list[dict]:
    """Measure every workload at every batch size, then its Python-loop latency; end with a peak-RSS summary.

    Each result is passed to `report` as soon as it is measured and all are returned in order. With
    cold=False compilations may come from the caches (quick tests), so compile_s means little.
    """
    results = []

    def record(result: dict) -> None:
        results.append(result)
        report(result)

    with cold_compiles() if cold else contextlib.nullcontext():
        for workload in workloads:
            for batch in batches:
                record(measure_rollout(workload, batch, steps, cold))
            if loops:
                record(measure_python_loop(workload, loop_calls, cold))
    record(machine_summary("engine", compile_cache="disabled" if cold else "allowed"))
    return results


# ---------------------------------------------------------------- output

_HEADER = f"{'size':<6}{'batch':>7}  {'mode':<12}{'steps/s':>12}{'ms/call':>10}{'compile s':>11}"


def table_row(result: dict) -> str:
    """One line of the readable table for a result of `benchmark`."""
    if "peak_rss_mb" in result:
        return machine_row(result)
    warning = "" if result["finite"] else "  NON-FINITE STATE"
    if result.get("mode") == "python_loop":
        cells = f"{'python loop':<12}{'':>12}{result['latency_ms']:>10.3f}"
        if "pytree_latency_ms" in result:
            warning = f"  (pytree step {result['pytree_latency_ms']:.3f} ms){warning}"
    else:
        ms_per_call = 1000.0 * result["batch"] / result["steps_per_s"]  # one batched step
        cells = f"{'scan':<12}{result['steps_per_s']:>12,.0f}{ms_per_call:>10.3f}"
    devices = f"  ({result['devices']} devices)" if result.get("devices", 1) > 1 else ""
    return f"{result['size']:<6}{result['batch']:>7}  {cells}{result['compile_s']:>11.2f}{devices}{warning}"


def run(args: argparse.Namespace) -> int:
    if args.level:
        try:
            workloads = [level_workload(args.level)]
        except ImportError:
            print(NO_LEVEL_LOADER, file=sys.stderr)
            return 2
        except (OSError, ValueError) as error:  # the loader's LevelError is a ValueError
            print(f"cannot load level {args.level}: {error}", file=sys.stderr)
            return 2
    else:
        workloads = builtin_workloads(args.sizes)

    if args.json:
        def report(result: dict) -> None:
            print(json.dumps(result), flush=True)
    else:
        print(f"jax2d engine, {args.steps} steps per rollout; compile times are cold "
              "(persistent compilation cache disabled, in-memory caches cleared)")
        print("scan: B scenes under vmap in one jitted lax.scan, steps/s = B * steps / s, ms/call = one batched step")
        print("python loop: one scene, one jitted step per call, blocking each call, in a child process on one core;")
        print("  compile s = its first call, measured in this process (a process that compiles keeps every core);")
        print("  state and params packed in one buffer each (jax2d.step_compact); the plain pytree step in brackets")
        print(_HEADER, flush=True)

        def report(result: dict) -> None:
            print(table_row(result), flush=True)

    loop_only = getattr(args, "loop_only", False)
    if loop_only:
        results = benchmark(workloads, [], args.steps, report=report)
    else:  # the loops' latencies come from a one-device, one-core child (interactive_loops)
        results = run_with_interactive_loops(
            functools.partial(benchmark, workloads, args.batches, args.steps, loop_calls=COMPILE_LOOP_CALLS), "engine",
            (["--level", args.level] if args.level else ["--sizes", ",".join(args.sizes)]) + backend_flag(args),
            report)
    return 0 if all(result.get("finite", True) for result in results) else 1
