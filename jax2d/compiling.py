"""`jax2d.jit`: `jax.jit` with the XLA options the engine compiles best under.

The step is hundreds of tiny array operations, and on the CPU XLA's newer MLIR fusion emitters spend
most of a compile on them. The older emitters (`xla_cpu_use_fusion_emitters=False`) produce the same
kernels in less time, and faster ones under `vmap`. Measured on the 2-core reference machine
(25 Nov 2026), one process, the two programs compiled side by side and their runs interleaved:

- cold compile of one l-size step: 5.0-5.75 s -> 3.2-3.8 s of XLA time (trace ~1.2 s on top);
- 200-step scans at batch 256, one device: s 53k -> 71k, m 36k -> 43k, l 8.3k -> 12.5k steps/s (medians);
- PPO training chunks (m, 32 envs): same speed within noise, compile 30.4 -> 28.2 s;
- one scene stepped from a Python loop: about 5 % slower (l 0.640 -> 0.671 ms, m 0.30 -> 0.32 ms).

The options are per computation (`jax.jit(compiler_options=...)`), so programs that import jax2d
keep their own defaults, and the persistent compilation cache keys on them. Everything in this
project jits through here (ruff's banned-api rule TID251 enforces it).

Options are per backend: XLA refuses an option its backend does not know (on CUDA every compile failed
with "No such compile option: 'xla_cpu_use_fusion_emitters'"), so each call compiles with the options
of the platform it runs on (`options_for`), found the way JAX places the call (`call_platform`):
committed arguments, then the jit's device, then `jax.default_device`, then the default backend.

For experiments, `JAX2D_COMPILER_OPTIONS` (a JSON object, read when a function is jitted, so set it before the
process starts) changes the options without editing code: a value replaces ours, and null removes one, which
leaves XLA's default or XLA_FLAGS' value (kinetix.bench.gpu's "eager" variant removes the CUDA-graph options
this way, so that a profile sees every kernel). A caller's `compiler_options` still win.
"""

from __future__ import annotations

import functools
import json
import os
from collections.abc import Callable, Iterable
from typing import Any

import jax
from jax._src import core as _core  # trace_state_clean: JAX has no public "am I inside a trace" test
from jax._src import xla_bridge as _xla_bridge  # backends(): which platforms this process has

# The engine's options (see the module docstring). On a GPU, loops and conditionals go into CUDA graphs
# (command buffers) with the kernels around them: XLA's default puts only fusions and library calls there, and
# the step's loops over colours and joints then launched every iteration's kernels from the host and read its
# trip test back. Measured on one H200 (26 Nov 2026, bench/gpu.sh, batch 2,048): env s 470k -> 995k steps/s,
# engine s 1.19M -> 2.30M, env l 234k -> 436k. A step is then about 1,100 kernels of a few microseconds, each
# waiting for the one before; CONCURRENT scheduling orders the graph's nodes by their data alone, so independent
# kernels (the shapes' and joints' stages, say) run side by side. Measured on one H200 (27 Nov 2026, bench/gpu.sh,
# two calls, batch 2,048, set through XLA_FLAGS): env s 937k-943k -> 1.10M steps/s (+16 %), env l 402k -> 460k
# (+14 %), bitwise the same on a rerun (docs/gpu.md).
GPU_COMMAND_BUFFERS = "FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,WHILE,CONDITIONAL"
# On the CPU, YNNPACK takes only single matrix products (the networks' layers), not reductions: by default XLA
# hands short reductions to it too, as library calls each dearer than the loop XLA writes itself (~50 in env s's
# rollout: a polygon's vertices, a pair's minimum, the env's NaN check). Measured on the 2-core machine (27 Nov
# 2026, quiet, alternating processes, env rollout of the reference levels on two devices, steps/s): s 256
# 89-92k -> 94-96k, m 256 42-46k -> 49k, l 256 14.6-14.8k -> 14.9-15.8k; s 16, s 2048 and batch 1 within
# noise; PPO training at s, 512 envs (`kinetix bench train`), 4.8-5.0k both ways.
CPU_LIBRARY_FUSIONS = "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT"
COMPILER_OPTIONS: dict[str, Any] = {
    "xla_cpu_use_fusion_emitters": False,
    "xla_cpu_experimental_ynn_fusion_type": CPU_LIBRARY_FUSIONS,
    "xla_gpu_enable_command_buffer": GPU_COMMAND_BUFFERS,
    "xla_gpu_command_buffer_scheduling_mode": "CONCURRENT",
}
# An option named with one of these prefixes exists only in those platforms' compilers. JAX names a GPU
# device's platform "gpu" and its backend "cuda" or "rocm"; all three are accepted here.
PLATFORM_PREFIXES: dict[str, tuple[str, ...]] = {
    "xla_cpu_": ("cpu",),
    "xla_gpu_": ("gpu", "cuda", "rocm"),
    "xla_tpu_": ("tpu",),
}


def options_for(platform: str, options: dict[str, Any]) -> dict[str, Any]:
    """The part of `options` that the compiler of `platform` ("cpu", "gpu", "cuda", "rocm", "tpu") accepts:
    every option but those named for another platform (`PLATFORM_PREFIXES`)."""
    platform = platform.lower()
    return {name: value for name, value in options.items()
            if all(platform in platforms or not name.startswith(prefix)
                   for prefix, platforms in PLATFORM_PREFIXES.items())}


_probe_jit = jax.jit  # noqa: TID251 - probing an option is compiling without the engine's options
# (platform, option, repr(value)) -> XLA's message where its compiler refused the option, None where it took it
_PROBED: dict[tuple[str, str, str], str | None] = {}


def _refusal(platform: str, name: str, value: Any) -> str | None:
    """Why the platform's compiler refuses `name=value` (None if it accepts it), found once per process by
    compiling a tiny program with it. An error that is not about the option (no such backend here) counts as
    accepted: the call that needs the platform will say what is wrong."""
    key = (platform, name, repr(value))
    if key not in _PROBED:
        message = None
        try:
            on = jax.sharding.SingleDeviceSharding(jax.devices(platform)[0])
            _probe_jit(lambda x: x + 1, compiler_options={name: value}).lower(
                jax.ShapeDtypeStruct((), jax.numpy.float32, sharding=on)).compile()
        except Exception as error:  # noqa: BLE001 - XLA reports a refused option as a runtime error
            first = str(error).splitlines()[0]
            message = first if "option" in first.lower() else None
        _PROBED[key] = message
    return _PROBED[key]


def accepted_options(platform: str, options: dict[str, Any]) -> dict[str, Any]:
    """`options_for(platform, options)` less those this JAX's compiler for the platform refuses.

    XLA's options come and go between versions (jax 0.11's CPU compiler no longer knows
    `xla_cpu_use_fusion_emitters`, and every CPU compile through here failed on it on a GPU machine), so each
    option is tried once per platform and process, on a tiny program, and one that fails is left out with a
    warning (once) rather than failing every compile."""
    import warnings

    kept = {}
    for name, value in options_for(platform, options).items():
        new = (platform, name, repr(value)) not in _PROBED
        message = _refusal(platform, name, value)
        if message is None:
            kept[name] = value
        elif new:
            warnings.warn(f"jax2d: {platform} compiles without {name}={value!r}: {message}", stacklevel=3)
    return kept


@functools.cache
def only_platform() -> str | None:
    """The platform when this process has one backend (a CPU-only machine: every call is on the CPU), else None
    (a GPU machine has the GPU's and the CPU's). Cached: JAX starts its backends once per process."""
    platforms = {backend.platform for backend in _xla_bridge.backends().values()}
    return platforms.pop() if len(platforms) == 1 else None


def _platform_of(where: Any) -> str | None:
    """The platform of a Device, a platform name (as `jax.default_device` accepts) or a Sharding; None if none."""
    if where is None:
        return None
    if isinstance(where, str):
        return where
    if isinstance(where, jax.sharding.Sharding):
        return next(iter(where.device_set)).platform
    return where.platform


def call_platform(leaves: Iterable[Any], fixed: str | None = None, default_device: Any = None,
                  default_backend: str | None = None) -> str:
    """The platform a top-level jitted call runs on, decided as JAX decides it: a committed array argument
    (`jax.device_put` to a device), then the jit's own device or backend (`fixed`), then `jax.default_device`
    (`default_device`, read from JAX's config when None), then the default backend."""
    for leaf in leaves:
        if isinstance(leaf, jax.Array) and leaf.committed:
            return next(iter(leaf.devices())).platform
    return (fixed or _platform_of(default_device if default_device is not None else jax.config.jax_default_device)
            or default_backend or jax.default_backend())


def _fixed_platform(kwargs: dict[str, Any]) -> str | None:
    """The platform a jit's own arguments pin it to (device=, backend=, or concrete shardings), if any."""
    if kwargs.get("device") is not None:
        return kwargs["device"].platform
    if kwargs.get("backend") is not None:
        return kwargs["backend"]
    for name in ("in_shardings", "out_shardings"):
        shardings = [s for s in jax.tree.leaves(kwargs.get(name)) if isinstance(s, jax.sharding.Sharding)]
        if shardings:
            return _platform_of(shardings[0])
    return None


class Jitted:
    """A function jitted with the engine's options (per platform) when called from Python, plainly inside a trace.

    JAX accepts compiler options only on the outermost jit (a nested one raises ValueError), and a
    nested jit is compiled as part of its caller anyway, under the caller's options. So a function
    jitted here can be called anywhere a `jax.jit` function can. Attributes (`lower`, `trace`,
    `eval_shape`, ...) are those of the top-level version for the default platform.

    A top-level version is made per platform on first use. In a process with one backend (a CPU-only machine)
    the platform is known without looking at the arguments; with several (a GPU machine, whose CPU is a backend
    too) every call looks for a committed argument first.
    """

    def __init__(self, fun: Callable, options: dict[str, Any], kwargs: dict[str, Any]) -> None:
        functools.update_wrapper(self, fun)  # first: it copies fun.__dict__, which must not replace the jits below
        self._fun, self._options, self._kwargs = fun, options, kwargs
        self._fixed = _fixed_platform(kwargs)
        self._by_platform: dict[str, Callable] = {}
        self._nested = jax.jit(fun, **kwargs)  # noqa: TID251 - the one place

    def _top_for(self, platform: str) -> Callable:
        jitted = self._by_platform.get(platform)
        if jitted is None:
            options = accepted_options(platform, self._options) or None
            jitted = jax.jit(self._fun, compiler_options=options, **self._kwargs)  # noqa: TID251 - the one place
            jitted = self._by_platform.setdefault(platform, jitted)  # another thread may have been first
        return jitted

    @property
    def _top(self) -> Callable:
        """The top-level version for calls with no committed argument."""
        return self._top_for(only_platform() or call_platform((), self._fixed))

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        if not _core.trace_state_clean():
            return self._nested(*args, **kwargs)
        platform = only_platform() or call_platform(jax.tree.leaves((args, kwargs)), self._fixed)
        return self._top_for(platform)(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        if name in ("_fun", "_options", "_kwargs", "_fixed", "_by_platform", "_nested"):
            raise AttributeError(name)  # not yet set (copying, unpickling): no recursion
        return getattr(self._top, name)

    def __get__(self, obj: Any, objtype: Any = None) -> Any:  # as a method decorator, like jax.jit
        return self if obj is None else functools.partial(self, obj)


OPTIONS_VARIABLE = "JAX2D_COMPILER_OPTIONS"


def environment_options() -> dict[str, Any]:
    """The overrides in JAX2D_COMPILER_OPTIONS: a JSON object of option -> value (null: drop our value)."""
    raw = os.environ.get(OPTIONS_VARIABLE, "").strip()
    if not raw:
        return {}
    example = '{"xla_gpu_enable_command_buffer": null}'
    try:
        options = json.loads(raw)
    except json.JSONDecodeError as error:
        raise ValueError(f"{OPTIONS_VARIABLE} is not JSON ({error}): give an object such as {example}") from None
    if not isinstance(options, dict) or not all(isinstance(name, str) for name in options):
        raise ValueError(f"{OPTIONS_VARIABLE} must be a JSON object of XLA option names, such as {example}; "
                         f"got {raw[:200]!r}")
    return options


def jit(fun: Callable, /, **kwargs: Any) -> Jitted:
    """`jax.jit(fun, **kwargs)` that compiles with COMPILER_OPTIONS (then JAX2D_COMPILER_OPTIONS' overrides; a
    caller's `compiler_options` win), less those the call's platform does not accept, when called from Python; an
    ordinary nested jit inside a trace."""
    options = {**COMPILER_OPTIONS, **environment_options(), **(kwargs.pop("compiler_options", None) or {})}
    options = {name: value for name, value in options.items() if value is not None}
    return Jitted(fun, options, kwargs)
