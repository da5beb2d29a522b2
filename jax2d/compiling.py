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
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
from jax._src import core as _core  # trace_state_clean: JAX has no public "am I inside a trace" test

COMPILER_OPTIONS: dict[str, Any] = {"xla_cpu_use_fusion_emitters": False}


class Jitted:
    """A function jitted twice: with the engine's options when called from Python, plainly inside a trace.

    JAX accepts compiler options only on the outermost jit (a nested one raises ValueError), and a
    nested jit is compiled as part of its caller anyway, under the caller's options. So a function
    jitted here can be called anywhere a `jax.jit` function can. Attributes (`lower`, `trace`,
    `eval_shape`, ...) are those of the top-level version.
    """

    def __init__(self, fun: Callable, options: dict[str, Any], kwargs: dict[str, Any]) -> None:
        functools.update_wrapper(self, fun)  # first: it copies fun.__dict__, which must not replace the jits below
        self._top = jax.jit(fun, compiler_options=options, **kwargs)  # noqa: TID251 - the one place
        self._nested = jax.jit(fun, **kwargs)  # noqa: TID251 - the one place

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return (self._top if _core.trace_state_clean() else self._nested)(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        if name in ("_top", "_nested"):  # not yet set (copying, unpickling): no recursion
            raise AttributeError(name)
        return getattr(self._top, name)

    def __get__(self, obj: Any, objtype: Any = None) -> Any:  # as a method decorator, like jax.jit
        return self if obj is None else functools.partial(self, obj)


def jit(fun: Callable, /, **kwargs: Any) -> Jitted:
    """`jax.jit(fun, **kwargs)` that compiles with COMPILER_OPTIONS (a caller's `compiler_options` win)
    when called from Python, and is an ordinary nested jit when called inside another trace."""
    options = {**COMPILER_OPTIONS, **(kwargs.pop("compiler_options", None) or {})}
    return Jitted(fun, options, kwargs)
