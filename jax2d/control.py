"""How the step's data-dependent control flow is compiled (SolverConfig.control_flow), and per-platform choices.

The step skips work that no scene of the batch needs, in three ways: the loops over colours and joint slots
visit only the live ones (a trip count read from the data, sweeps.schedule and joint_solver.schedule); whole
stages sit in a conditional on whether any scene needs them (restitution, the static walls' sweep back and
push-out); and `math2d.stored` keeps a result in memory by putting it in a conditional that is always true.
That is "skip", the default. "fixed" runs every loop its full static count, in slot order, every stage always,
and stores nothing by a conditional, so no trip count or predicate is read from the data. Both compute the
same to rounding: an empty colour has zero masses and impulses and an inactive joint slot zero selections, so
solving them changes nothing, and each skipped stage changes nothing in scenes that do not need it.

Fixed was written for GPUs, where XLA reads each loop test and predicate back to the host before it launches
what follows. Measured on one H200 (26 Nov 2026, bench/gpu.sh, batch 2,048, steps/s): the extra work cost more
than the waits it saved. Env s 470k skip / 305k fixed, engine s 1.19M / 676k, env l 234k / 140k; with loops
and conditionals in CUDA graphs (jax2d.compiling's GPU option) 995k / 329k, 2.30M / 663k, 436k / 107k. On the
2-core CPU fixed was 2.6-3.5x slower. So skip is the default on every platform.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax

from jax2d import compiling

FIXED = "fixed"  # SolverConfig.control_flow


def per_platform(cpu: Callable, other: Callable, *args: Any) -> Any:
    """cpu(*args) in a program compiled for the CPU, other(*args) in one compiled for any other platform.

    In a process with one backend (a CPU-only machine) this is decided here and only one is traced. With
    several (a GPU machine also has the CPU) both are traced and `lax.platform_dependent` leaves XLA the one
    of the platform it compiles for."""
    only = compiling.only_platform()
    if only is not None:
        return (cpu if only == "cpu" else other)(*args)
    return jax.lax.platform_dependent(*args, cpu=cpu, default=other)


def if_any(fixed: bool, needed: jax.Array, run: Callable[[], Any], otherwise: Callable[[], Any]) -> Any:
    """run() where some element of `needed` is true, else otherwise(): a conditional (skip), or always run()
    (fixed; `run` must then change nothing where nothing needs it)."""
    if fixed:
        return run()
    return jax.lax.cond(jax.numpy.any(needed), run, otherwise)
