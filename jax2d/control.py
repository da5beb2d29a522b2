"""How the step's data-dependent control flow is compiled: skipped work on the CPU, fixed counts elsewhere.

The step skips work that no scene of the batch needs, in three ways: the loops over colours and joint slots
visit only the live ones (a trip count read from the data, sweeps.schedule and joint_solver.schedule); whole
stages sit in a conditional on whether any scene needs them (restitution, the static walls' sweep back and
push-out); and `math2d.stored` keeps a result in memory by putting it in a conditional that is always true.
On the CPU this is the least work, and reading a loop's test or a predicate costs nothing. A GPU computes the
test on the device and XLA reads it back to the host before it launches what follows: one wait per loop
iteration and per conditional, each longer than most of the step's kernels.

So a config's `control_flow` (SolverConfig) is "skip" on the CPU and "fixed" elsewhere ("auto", the default,
picks by the platform the step is compiled for). Fixed: every loop runs its full static count, in slot order
(XLA knows the trip count and reads no predicate), every stage runs, nothing is stored by a conditional. Both
compute the same: an empty colour has zero masses and impulses and an inactive joint slot zero selections, so
solving them changes nothing, and each skipped stage changes nothing in scenes that do not need it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax

from jax2d import compiling
from jax2d.state import SolverConfig

SKIP, FIXED = "skip", "fixed"


def per_platform(cpu: Callable, other: Callable, *args: Any) -> Any:
    """cpu(*args) in a program compiled for the CPU, other(*args) in one compiled for any other platform.

    In a process with one backend (a CPU-only machine) this is decided here and only one is traced. With
    several (a GPU machine also has the CPU) both are traced and `lax.platform_dependent` leaves XLA the one
    of the platform it compiles for."""
    only = compiling.only_platform()
    if only is not None:
        return (cpu if only == "cpu" else other)(*args)
    return jax.lax.platform_dependent(*args, cpu=cpu, default=other)


def resolved(config: SolverConfig, platform_is_cpu: bool) -> SolverConfig:
    """`config` with "auto" control flow made concrete for a program on the CPU (skip) or elsewhere (fixed)."""
    if config.control_flow != "auto":
        return config
    return dataclasses.replace(config, control_flow=SKIP if platform_is_cpu else FIXED)


def if_any(fixed: bool, needed: jax.Array, run: Callable[[], Any], otherwise: Callable[[], Any]) -> Any:
    """run() where some element of `needed` is true, else otherwise(): a conditional (skip), or always run()
    (fixed; `run` must then change nothing where nothing needs it)."""
    if fixed:
        return run()
    return jax.lax.cond(jax.numpy.any(needed), run, otherwise)
