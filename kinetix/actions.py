"""Action spaces: what the agent outputs, and how it becomes binding values.

Every action type maps to the same unified binding values: one value in [-1, 1] per motor
binding (4) and one in [0, 1] per thruster binding (2). `kinetix.bindings.expand_actions` then
gives every joint the value of its binding (so joints sharing a binding always move together).

    multi_discrete  int32 (6,): motor binding i takes {0: off, 1: +1, 2: -1}; thruster binding j
                    takes {0: off, 1: on}. nvec = (3, 3, 3, 3, 2, 2). The public Kinetix's code
                    mapping (its docs say [0, -1, +1], its code does 1 -> +1, 2 -> -1).
    discrete        int32 scalar in [0, 11): a < 8 drives motor binding a // 2 at -1 (a even) or
                    +1 (a odd); a == 8 does nothing; 9 and 10 fire thruster binding 0 or 1.
    continuous      float32 (6,): motors clipped to [-1, 1], thrusters clipped to [0, 1].

Out-of-range discrete values act as "off" for that binding, never as another action.
The small space classes below also describe observations (see kinetix.env).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from kinetix.bindings import expand_actions
from kinetix.level import NUM_MOTOR_BINDINGS, NUM_THRUSTER_BINDINGS, Level

ACTION_TYPES = ("multi_discrete", "discrete", "continuous")
NUM_BINDINGS = NUM_MOTOR_BINDINGS + NUM_THRUSTER_BINDINGS
NUM_DISCRETE = 2 * NUM_MOTOR_BINDINGS + 1 + NUM_THRUSTER_BINDINGS  # 11
DISCRETE_NOOP = 2 * NUM_MOTOR_BINDINGS  # 8


# ---------------------------------------------------------------- space descriptions


@dataclasses.dataclass(frozen=True)
class Discrete:
    """An integer in [0, n)."""

    n: int
    shape: tuple[int, ...] = ()
    dtype: np.dtype = np.dtype(np.int32)

    def sample(self, key: jax.Array) -> jax.Array:
        return jax.random.randint(key, self.shape, 0, self.n, jnp.int32)

    def contains(self, x) -> bool:
        x = np.asarray(x)
        return x.shape == self.shape and np.issubdtype(x.dtype, np.integer) and bool(np.all((x >= 0) & (x < self.n)))


@dataclasses.dataclass(frozen=True)
class MultiDiscrete:
    """A vector of integers, entry i in [0, nvec[i])."""

    nvec: tuple[int, ...]
    dtype: np.dtype = np.dtype(np.int32)

    @property
    def shape(self) -> tuple[int, ...]:
        return (len(self.nvec),)

    def sample(self, key: jax.Array) -> jax.Array:
        return jax.random.randint(key, self.shape, 0, jnp.asarray(self.nvec, jnp.int32), jnp.int32)

    def contains(self, x) -> bool:
        x = np.asarray(x)
        return (x.shape == self.shape and np.issubdtype(x.dtype, np.integer)
                and bool(np.all((x >= 0) & (x < np.asarray(self.nvec)))))


@dataclasses.dataclass(frozen=True)
class Box:
    """An array of `shape` with entries in [low, high] (scalars or per-entry tuples)."""

    low: float | tuple[float, ...]
    high: float | tuple[float, ...]
    shape: tuple[int, ...]
    dtype: np.dtype = np.dtype(np.float32)

    def sample(self, key: jax.Array) -> jax.Array:
        """Uniform in [low, high]; only for finite bounds and float dtypes."""
        low = jnp.broadcast_to(jnp.asarray(self.low, jnp.float32), self.shape)
        high = jnp.broadcast_to(jnp.asarray(self.high, jnp.float32), self.shape)
        return jax.random.uniform(key, self.shape, jnp.float32, low, high).astype(self.dtype)

    def contains(self, x) -> bool:
        x = np.asarray(x)
        return x.shape == self.shape and bool(np.all((x >= np.asarray(self.low)) & (x <= np.asarray(self.high))))


@dataclasses.dataclass(frozen=True)
class DictSpace:
    """Named sub-spaces (an observation dict)."""

    spaces: dict

    def __getitem__(self, name: str):
        return self.spaces[name]

    def sample(self, key: jax.Array) -> dict:
        keys = jax.random.split(key, len(self.spaces))
        return {name: space.sample(k) for (name, space), k in zip(self.spaces.items(), keys, strict=True)}

    def contains(self, x) -> bool:
        return set(x) == set(self.spaces) and all(space.contains(x[name]) for name, space in self.spaces.items())


Space = Discrete | MultiDiscrete | Box | DictSpace


# ---------------------------------------------------------------- actions


def check_action_type(action_type) -> str:
    """The action type name; accepts the name or anything with an `.action` name (an EnvConfig)."""
    action_type = getattr(action_type, "action", action_type)
    if action_type not in ACTION_TYPES:
        raise ValueError(f"unknown action type {action_type!r}: use one of {', '.join(ACTION_TYPES)}")
    return action_type


def action_space(action_type) -> Space:
    action_type = check_action_type(action_type)
    if action_type == "multi_discrete":
        return MultiDiscrete((3,) * NUM_MOTOR_BINDINGS + (2,) * NUM_THRUSTER_BINDINGS)
    if action_type == "discrete":
        return Discrete(NUM_DISCRETE)
    return Box((-1.0,) * NUM_MOTOR_BINDINGS + (0.0,) * NUM_THRUSTER_BINDINGS, 1.0, (NUM_BINDINGS,))


def policy_outputs(action_type) -> int:
    """How many numbers a policy head emits: logits (16 multi-discrete, 11 discrete) or means (6 continuous)."""
    space = action_space(action_type)
    if isinstance(space, MultiDiscrete):
        return int(sum(space.nvec))
    if isinstance(space, Discrete):
        return space.n
    return NUM_BINDINGS


def binding_values(action: jax.Array, action_type) -> tuple[jax.Array, jax.Array]:
    """(motor binding values (4,) in [-1, 1], thruster binding values (2,) in [0, 1]) for one action."""
    action_type = check_action_type(action_type)
    M = NUM_MOTOR_BINDINGS
    if action_type == "multi_discrete":
        a = jnp.asarray(action).astype(jnp.int32)
        motor = jnp.where(a[:M] == 1, 1.0, jnp.where(a[:M] == 2, -1.0, 0.0))
        thrust = (a[M:] == 1).astype(jnp.float32)
        return motor.astype(jnp.float32), thrust
    if action_type == "discrete":
        a = jnp.asarray(action).astype(jnp.int32)
        sign = jnp.where(a % 2 == 0, -1.0, 1.0)
        motor = jnp.where((a < 2 * M) & (jnp.arange(M) == a // 2), sign, 0.0)
        thrust = (jnp.arange(NUM_THRUSTER_BINDINGS) == a - (2 * M + 1)).astype(jnp.float32)
        return motor.astype(jnp.float32), thrust
    a = jnp.nan_to_num(jnp.asarray(action, jnp.float32))  # a NaN action would otherwise reach the solver
    return jnp.clip(a[:M], -1.0, 1.0), jnp.clip(a[M:], 0.0, 1.0)


def level_actions(level: Level, action: jax.Array, action_type) -> tuple[jax.Array, jax.Array]:
    """(motor actions (J,), thruster actions (T,)) for jax2d.step: the action, expanded through the bindings."""
    return expand_actions(level, *binding_values(action, action_type))


def noop_action(action_type) -> jax.Array:
    """The action that drives nothing (motor_auto joints still turn). `action_type`: a name or an EnvConfig."""
    action_type = check_action_type(action_type)
    if action_type == "multi_discrete":
        return jnp.zeros((NUM_BINDINGS,), jnp.int32)
    if action_type == "discrete":
        return jnp.asarray(DISCRETE_NOOP, jnp.int32)
    return jnp.zeros((NUM_BINDINGS,), jnp.float32)


def sample_random_action(key: jax.Array, action_type) -> jax.Array:
    """A uniformly random action of this type (a name or an EnvConfig)."""
    return action_space(action_type).sample(key)
