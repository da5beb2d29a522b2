"""`kinetix validate FILE...`: load each level (either format) and simulate it with random actions.

A file passes when it loads and its state stays finite through the whole run. Files are
grouped by capacity and each group runs as one vmapped, jitted `lax.scan`, so every capacity
compiles once however many files share it.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import sys
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

import jax2d
from kinetix.bindings import expand_actions
from kinetix.env import all_finite
from kinetix.level import NUM_MOTOR_BINDINGS, NUM_THRUSTER_BINDINGS, Level, LevelError, LevelFile
from kinetix.levels import load_level

DEFAULT_STEPS = 1000
DEFAULT_CONFIG = jax2d.SolverConfig()


@dataclasses.dataclass(frozen=True)
class Result:
    path: str
    error: str | None  # None: the level passed
    warnings: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        return self.error is None

    def line(self) -> str:
        return f"OK  {self.path}" if self.ok else f"FAIL {self.path}: {self.error}"


def _run_one(level: Level, params: jax2d.SimParams, key: jax.Array, steps: int, config: jax2d.SolverConfig):
    def one_step(carry, step_key):
        state, finite = carry
        motor_key, thruster_key = jax.random.split(step_key)
        motor_values = jax.random.uniform(motor_key, (NUM_MOTOR_BINDINGS,), minval=-1.0, maxval=1.0)
        thruster_values = jax.random.uniform(thruster_key, (NUM_THRUSTER_BINDINGS,))
        motor, thrust = expand_actions(level, motor_values, thruster_values)
        state = jax2d.step(state, params, motor, thrust, config)
        return (state, finite & all_finite(state)), None

    (state, finite), _ = jax.lax.scan(one_step, (level.sim, all_finite(level.sim)), jax.random.split(key, steps))
    return state, finite


@functools.partial(jax2d.jit, static_argnames=("steps", "config"))
def _simulate(levels, params, keys, steps, config):
    # One compiled program per (capacity, batch, steps, config).
    return jax.vmap(lambda level, p, key: _run_one(level, p, key, steps, config))(levels, params, keys)


def simulate(levels: Level, params: jax2d.SimParams, keys: jax.Array, steps: int = DEFAULT_STEPS,
             config: jax2d.SolverConfig = DEFAULT_CONFIG) -> tuple[jax2d.SimState, jax.Array]:
    """Run a batch of levels (stacked, one capacity) `steps` physics steps with uniform random binding values.

    Returns the final states and, per level, whether every float in the state stayed finite throughout.
    """
    return _simulate(levels, params, keys, steps=steps, config=config)


def stack(items: Sequence) -> object:
    """Stack pytrees of one structure along a new leading axis."""
    return jax.tree.map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *items)


def simulate_files(files: Sequence[LevelFile], seed: int = 0, steps: int = DEFAULT_STEPS) -> list[bool]:
    """For each loaded level, whether it stayed finite for `steps` steps; one compiled run per capacity."""
    finite = [False] * len(files)
    groups: dict[object, list[int]] = {}
    for i, file in enumerate(files):
        groups.setdefault(file.level.capacity, []).append(i)
    for members in groups.values():
        levels = stack([files[i].level for i in members])
        params = stack([files[i].params.sim_params() for i in members])
        keys = jnp.stack([jax.random.fold_in(jax.random.key(seed), i) for i in members])
        _, ok = simulate(levels, params, keys, steps)
        for i, value in zip(members, np.asarray(ok), strict=True):
            finite[i] = bool(value)
    return finite


def validate(paths: Sequence[str], seed: int = 0, steps: int = DEFAULT_STEPS) -> list[Result]:
    """Load and simulate every path; one Result per path, in order."""
    results: list[Result | None] = [None] * len(paths)
    loaded: list[tuple[int, LevelFile]] = []
    for i, path in enumerate(paths):
        try:
            loaded.append((i, load_level(path)))
        except LevelError as error:
            results[i] = Result(str(path), str(error))
    finite = simulate_files([file for _, file in loaded], seed, steps)
    for (i, file), ok in zip(loaded, finite, strict=True):
        error = None if ok else f"state became NaN or infinite within {steps} steps of random actions"
        results[i] = Result(str(paths[i]), error, file.warnings)
    return results


def run(args: argparse.Namespace) -> int:
    results = validate(args.files, seed=args.seed, steps=args.steps)
    for result in results:
        print(result.line(), flush=True)
        for warning in result.warnings:
            print(f"{result.path}: warning: {warning}", file=sys.stderr)
    failed = sum(not r.ok for r in results)
    if failed:
        print(f"{failed} of {len(results)} level files failed", file=sys.stderr)
    return 1 if failed else 0
