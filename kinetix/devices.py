"""Spread a batch of scenes over the CPU's cores.

XLA runs one computation on about one core of the CPU. Asking it for one CPU device per core
(`--xla_force_host_platform_device_count`) and splitting the batch axis over those devices
runs the halves side by side; every scene is independent, so no data moves between them
inside a step. XLA reads the flag once, when JAX starts its backend, so `request_cpu_devices`
must run before the first computation; the rest works with whatever devices exist.
"""

from __future__ import annotations

import os
import sys
import warnings

DEVICE_COUNT_FLAG = "--xla_force_host_platform_device_count"
BATCH_AXIS = "batch"


def request_cpu_devices(count: int | None = None) -> None:
    """Ask XLA for `count` CPU devices (default: one per core) before JAX starts.

    Leaves XLA_FLAGS alone when it already sets the device count (the caller's choice wins),
    and warns when JAX's backend is already running, since the flag would then have no effect.
    """
    count = count or os.cpu_count() or 1
    flags = os.environ.get("XLA_FLAGS", "")
    if DEVICE_COUNT_FLAG in flags or count == 1:
        return
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        warnings.warn(f"JAX is already running; {DEVICE_COUNT_FLAG}={count} is ignored", stacklevel=2)
        return
    os.environ["XLA_FLAGS"] = f"{flags} {DEVICE_COUNT_FLAG}={count}".strip()


def usable_cores() -> int:
    """How many CPU cores this process may run on (its affinity, where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def confine_to_one_core(core: int | None = None) -> bool:
    """Run this process (and every thread it starts later) on one CPU core; call it before JAX starts.

    For one scene stepped from a Python loop this is the fastest set-up measured on this 2-core machine:
    XLA sizes its thread pool from the cores it may use, so it gets one thread and runs the step's
    hundreds of tiny kernels without handing them across cores. A jitted l-size step called in a loop
    took 0.41-0.48 ms confined against 0.59-0.68 ms free (env.step at l: 0.89-0.94 against 1.13-1.33 ms).
    Batches want every core instead (`request_cpu_devices`). Returns False where the OS has no CPU affinity.
    """
    if not hasattr(os, "sched_setaffinity"):
        return False
    allowed = sorted(os.sched_getaffinity(0))
    core = allowed[0] if core is None else core
    if core not in allowed:
        raise ValueError(f"core {core} is not available to this process (allowed: {allowed})")
    # Threads started before this keep their cores, and importing jaxlib starts some: set it first.
    os.sched_setaffinity(0, {core})
    if "jax" in sys.modules:
        from jax._src import xla_bridge

        if xla_bridge.backends_are_initialized():
            warnings.warn("JAX is already running: its threads keep their cores and its pool its size; confine "
                          "before the first computation", stacklevel=2)
    return True


def batch_devices(batch: int) -> int:
    """How many devices a batch of this size is split over: all of them when they divide it, else 1."""
    import jax

    count = jax.device_count()
    return count if batch % count == 0 else 1


def local_mesh(devices: list | None = None):
    """A 1-D mesh over `devices` (default: all local devices) with axis name BATCH_AXIS."""
    import jax
    import numpy as np
    from jax.sharding import Mesh

    return Mesh(np.asarray(devices if devices is not None else jax.local_devices()), (BATCH_AXIS,))


def batch_sharding(batch: int, axis: int = 0):
    """A sharding that splits array axis `axis` (of size `batch`) over the devices, or None for one device."""
    import jax
    from jax.sharding import NamedSharding, PartitionSpec

    if batch_devices(batch) == 1:
        return None
    return NamedSharding(local_mesh(jax.devices()), PartitionSpec(*([None] * axis), BATCH_AXIS))


def shard_batch(tree, batch: int, axis: int = 0):
    """Place every leaf of `tree` (each with the batch at `axis`) split over the devices. Outside jit."""
    import jax

    sharding = batch_sharding(batch, axis)
    return tree if sharding is None else jax.device_put(tree, sharding)


def per_device(fn, batch: int, in_axes: tuple, out_axis: int = 0):
    """`fn` run on each device's part of the batch (shard_map), with nothing exchanged between devices.

    in_axes: like vmap's, one per positional argument: the axis of size `batch`, or None for an argument
    every device gets whole. Every output leaf has the batch at `out_axis`. With one device (or a batch
    the devices do not divide) this is `fn` itself.

    Why not let jit's partitioner split the batch: jax2d's step skips the colours that are empty in every
    scene of its batch, and under the partitioner that "every scene" spans devices, so each physics step
    ends in a cross-device all-reduce and the devices wait for each other (measured at batch 16: s 42k ->
    52k, m 29k -> 38k steps/s with shard_map). Here each device schedules its own scenes.
    """
    import jax
    from jax.sharding import PartitionSpec

    if batch_devices(batch) == 1:
        return fn

    def spec(axis):
        return PartitionSpec() if axis is None else PartitionSpec(*([None] * axis), BATCH_AXIS)

    # check_vma=False: the engine's always-true conditionals (jax2d.math2d.stored) have a constant branch
    # that shard_map's replication check would reject; every output is per device anyway.
    return jax.shard_map(fn, mesh=local_mesh(jax.devices()), in_specs=tuple(spec(a) for a in in_axes),
                         out_specs=spec(out_axis), check_vma=False)


# ---------------------------------------------------------------- backends (CPU, GPU)

# JAX tries every platform it knows at start-up, tpu included, and logs "Unable to initialize backend 'tpu': ...
# libtpu.so ..." on every machine without one (every `kinetix serve`, issue 37). Accelerators come as plugins (the
# `jax_plugins` entry points and namespace package: xla_cuda12, xla_cuda13, xla_rocm7, ...) or libtpu; each is
# present where its plugin is installed and its device file exists.
DEVICE_FILES = {"cuda": "/dev/nvidiactl", "rocm": "/dev/kfd", "tpu": "/dev/accel0"}


def _jax_plugins() -> set[str]:
    """The names of the JAX plugins installed (entry points of group jax_plugins, modules of jax_plugins.*)."""
    import importlib.metadata
    import importlib.util
    import pkgutil

    names = {entry.name for entry in importlib.metadata.entry_points(group="jax_plugins")}
    try:
        spec = importlib.util.find_spec("jax_plugins")
    except (ImportError, ValueError):
        spec = None
    if spec is not None and spec.submodule_search_locations:
        names.update(module.name for module in pkgutil.iter_modules(spec.submodule_search_locations))
    return names


def present_platforms() -> list[str] | None:
    """The JAX platforms of this machine, accelerators first and "cpu" last; None where a plugin is installed that
    this does not know (JAX then keeps its own choice)."""
    import importlib.util

    found: list[str] = []
    for plugin in sorted(_jax_plugins()):
        platform = next((name for name in ("cuda", "rocm") if name in plugin), None)
        if platform is None:
            return None
        if platform not in found and os.path.exists(DEVICE_FILES[platform]):
            found.append(platform)
    if importlib.util.find_spec("libtpu") is not None and os.path.exists(DEVICE_FILES["tpu"]):
        found.append("tpu")
    return [*found, "cpu"]


def use_present_platforms() -> None:
    """Before JAX starts: let it try only the platforms this machine has (JAX_PLATFORMS), so it does not log a
    failed attempt at the others. A JAX_PLATFORMS or jax_platforms the user set is left alone, as is a JAX that
    already started, or a machine with a plugin this does not know."""
    if os.environ.get("JAX_PLATFORMS"):
        return
    platforms = present_platforms()
    if platforms is None:
        return
    if "jax" not in sys.modules:
        os.environ["JAX_PLATFORMS"] = ",".join(platforms)  # read by JAX's config as it is imported
        return
    import jax
    from jax._src import xla_bridge

    if not xla_bridge.backends_are_initialized() and not jax.config.jax_platforms:
        jax.config.update("jax_platforms", ",".join(platforms))


BACKENDS = ("cpu", "gpu")  # what `kinetix bench ... --backend` accepts
GPU_INSTALL = "pip install -e '.[cuda]'"  # how to get JAX's CUDA backend (README, "Running on a GPU")


class BackendError(RuntimeError):
    """The backend asked for is not in this process (no GPU, or JAX already running on another)."""


def select_backend(name: str | None) -> None:
    """Make `name` ("cpu" or "gpu") JAX's backend for this process; None keeps JAX's choice (a GPU where there is
    one). Call it before the first computation: "cpu" hides every other backend from JAX (JAX_PLATFORMS=cpu);
    "gpu" only checks that JAX's default backend is a GPU, and raises BackendError where it is not."""
    if name is None:
        return
    if name not in BACKENDS:
        raise ValueError(f"unknown backend {name!r}; choose one of {', '.join(BACKENDS)}")
    import jax
    from jax._src import xla_bridge

    if name == "cpu":
        if xla_bridge.backends_are_initialized():
            if jax.default_backend() != "cpu":
                raise BackendError(f"JAX is already running on {jax.default_backend()}; choose the CPU before "
                                   "it starts")
            return
        jax.config.update("jax_platforms", "cpu")
        return
    if jax.default_backend() != "gpu":
        raise BackendError(f"no GPU backend in this process (JAX runs on {jax.default_backend()}); install JAX's "
                           f"CUDA wheels with `{GPU_INSTALL}`")


def backend_report() -> dict:
    """What a benchmark ran on: JAX's backend, the kind and count of its devices, and JAX's version."""
    import jax

    device = jax.devices()[0]
    return {"backend": jax.default_backend(), "device_kind": device.device_kind,
            "devices_available": jax.device_count(), "jax": jax.__version__}


def interactive_device():
    """The device for stepping one scene from Python (an interactive session), or None for JAX's default.

    One scene's step is thousands of tiny kernels; on a GPU each costs a launch, so a step called from Python took
    3.5 ms on an H100 against 0.3-0.45 ms on the CPU (issue 24). Where JAX's default backend is not the CPU, this is
    the first CPU device; where it is the CPU, None (placing anything would change nothing).
    """
    import jax

    return None if jax.default_backend() == "cpu" else jax.devices("cpu")[0]


def on_interactive_device(fn):
    """`fn` called with `jax.default_device(interactive_device())` (thread-local), so its computations on
    uncommitted arrays run there and its results stay there, uncommitted; `fn` itself where that is the default."""
    import functools

    import jax

    device = interactive_device()
    if device is None:
        return fn

    @functools.wraps(fn)
    def placed(*args, **kwargs):
        with jax.default_device(device):
            return fn(*args, **kwargs)

    return placed
