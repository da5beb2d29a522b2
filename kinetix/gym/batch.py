"""The device side of kinetix.gym: N environments stepped by one jitted call, their state never leaving the device.

Both Gymnasium classes drive a `Batch` (the single Env is a batch of one). One `step` call runs, for every
environment at once (vmap, split over the CPU devices like the JAX benchmarks: kinetix.devices.per_device):

    ended last step?  yes: a fresh episode from the reset function (the action is ignored; reward 0, not ended)
                      no:  kinetix.env's transition with the action
    then the observation, and the outputs (obs, reward, terminated, truncated, info) packed per environment into
    one uint32 row (jax2d.compact), so Python makes one device-to-host copy per step, whatever the observation.

That is Gymnasium's next-step autoreset (gymnasium.vector.AutoresetMode.NEXT_STEP). Keys: environment i's key
chain starts at `jax.random.split(jax.random.PRNGKey(seed), N)[i]`; every reset and every step of it draws the next
subkey (`key, sub = jax.random.split(key)`) and uses `sub`: an episode start is `env.reset(sub)` of kinetix.env, a
step `env.step_no_reset(sub, state, action, params)` (tests/kinetix/test_gym.py repeats this and compares bitwise).

Several level files: each keeps its own EnvParams (episode length, shaping, actuator scales); an episode's params are
those of the level kinetix.reset_fns.reset_list drew with the same key (`list_index`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os

import jax
import jax.numpy as jnp
import numpy as np

import jax2d
from jax2d.compact import Layout, pack
from kinetix.devices import batch_devices, per_device, shard_batch
from kinetix.env import EnvParams, EnvState, KinetixEnv, make_env
from kinetix.level_source import LevelSource
from kinetix.reset_fns import list_index

INFO_KEYS = ("solved", "failed", "nan", "distance", "timestep", "frozen")
# Built programs by content (Batch._program_key), so N equal single envs (SB3's DummyVecEnv, say) trace one
# program, not N: tracing the step of an l level takes seconds.
PROGRAM_CACHE_SIZE = 8
_PROGRAMS: dict[str, tuple] = {}


def _select_rows(mask, on_true, on_false):
    """Tree-wise select of whole rows (leading axis) by a (N,) mask."""
    return jax.tree.map(lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b), on_true,
                        on_false)


def _start_info(state: EnvState) -> dict:
    """The info of an episode's start (as kinetix.env's reset_compact): nothing happened yet."""
    false = jnp.asarray(False)
    return {"solved": false, "failed": false, "nan": false, "distance": state.last_distance,
            "timestep": state.timestep, "frozen": jnp.zeros((), jnp.int32)}


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Carry:
    """What stays on the device between calls, one row per environment."""

    key: jax.Array  # uint32 (2,): the environment's key chain
    state: EnvState
    params: EnvParams  # the current episode's
    ended: jax.Array  # bool: the last step ended the episode (the next step resets)


def host_rows(buffer: np.ndarray, layout: Layout):
    """The pytree of a (N, layout.size) uint32 array packed per row (vmap of jax2d.compact.pack), as numpy arrays
    with a leading axis N (views of `buffer`, no copies)."""
    leaves = []
    for shape, dtype, start in zip(layout.shapes, layout.dtypes, layout.offsets, strict=True):
        words = buffer[:, start:start + math.prod(shape)]
        leaf = words != 0 if dtype == np.dtype(bool) else words.view(dtype)
        leaves.append(leaf.reshape((buffer.shape[0], *shape)))
    return jax.tree.unflatten(layout.treedef, leaves)


class Batch:
    """`num_envs` environments of one level source on the device; reset and step return host (numpy) outputs."""

    def __init__(self, source: LevelSource, num_envs: int, observation: str = "entity",
                 action: str = "multi_discrete", pixel_resolution: int = 64, max_timesteps: int | None = None):
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if max_timesteps is not None and (isinstance(max_timesteps, bool) or not isinstance(max_timesteps, int)
                                          or max_timesteps < 1):
            raise ValueError(f"max_timesteps must be a positive integer, got {max_timesteps!r}")
        self.source = source
        self.num_envs = num_envs
        self.env: KinetixEnv = make_env(source.env_config(observation, action, pixel_resolution=pixel_resolution),
                                        source.reset_fn())
        override = {} if max_timesteps is None else {"max_timesteps": max_timesteps}
        self.params = dataclasses.replace(source.params, **override)
        # Per-level params only where levels can differ (a directory); else every episode has self.params.
        self.level_params = None
        if len(source.files) > 1:
            stacked = source.level_params
            if max_timesteps is not None:
                stacked = dataclasses.replace(stacked, max_timesteps=jnp.full(len(source.files), max_timesteps))
            self.level_params = stacked
        self.carry: Carry | None = None

        n = num_envs
        action_space = self.env.action_space
        self._false, self._no_keys = np.zeros(n, bool), np.zeros((n, 2), np.uint32)
        self._step_flags = None
        self._noop = np.zeros((n, *action_space.shape), np.float32 if action == "continuous" else np.int32)
        key = self._program_key(observation, action, pixel_resolution)
        if key in _PROGRAMS:  # an equal batch was built before: share its traced and compiled program
            self.env, self._carry_shape, self.layout, self._advance_jit = _PROGRAMS[key]
            return
        self._carry_shape = jax.eval_shape(jax.vmap(self._start), jax.ShapeDtypeStruct((n, 2), jnp.uint32))
        self.layout = jax.eval_shape(lambda key: self._start_outputs(self._start(key)), jax.random.PRNGKey(0)).layout
        # One program does every call, steps and resets alike (a reset is a step whose environments all start
        # over): one compilation per environment instead of three.
        self._advance_jit = jax2d.jit(per_device(self._advance, batch=n, in_axes=(0,) * 6), donate_argnums=(0,))
        if len(_PROGRAMS) >= PROGRAM_CACHE_SIZE:
            _PROGRAMS.pop(next(iter(_PROGRAMS)))
        _PROGRAMS[key] = (self.env, self._carry_shape, self.layout, self._advance_jit)

    def _program_key(self, observation: str, action: str, pixel_resolution: int) -> str:
        """What the program depends on: the settings, the levels' content (not their paths) and the params."""
        digest = hashlib.sha256(repr((self.source.spec if self.source.random else "files", self.source.size,
                                      self.source.frame_skip, self.source.solver, observation, action,
                                      pixel_resolution, self.num_envs, jax.device_count())).encode())
        content = (self.params, self.level_params, None if self.source.random else self.source.stacked)
        for leaf in jax.tree.leaves(content):
            array = np.asarray(leaf)
            digest.update(f"{array.dtype}{array.shape}".encode())
            digest.update(array.tobytes())
        return digest.hexdigest()

    # ------------------------------------------------------------ the program

    def _episode_params(self, key: jax.Array) -> EnvParams:
        if self.level_params is None:
            return jax.tree.map(jnp.asarray, self.params)
        i = list_index(key, len(self.source.files))
        return jax.tree.map(lambda x: x[i], self.level_params)

    def _start(self, key: jax.Array) -> Carry:
        """A fresh episode on key chain `key` (used for shapes; _advance starts episodes the same way)."""
        key, sub = jax.random.split(key)
        state = self.env.initial_state(sub)
        return Carry(key, state, self._episode_params(sub), jnp.asarray(False))

    def _start_outputs(self, carry: Carry):
        false = jnp.asarray(False)
        return pack(self._outputs(carry, 0.0, false, false, _start_info(carry.state)))

    def _outputs(self, carry: Carry, reward, terminated, truncated, info):
        return (self.env.observe(carry.state), jnp.asarray(reward, jnp.float32), terminated, truncated, info)

    def _advance(self, carry: Carry, actions, start: jax.Array, hold: jax.Array, new_keys: jax.Array,
                 use_new_keys: jax.Array):
        """A batch's call, per environment: start a new episode (asked by `start`, or because the last step ended
        it and `hold` is not set), keep the episode as it is (`hold`: a reset that leaves this environment alone),
        or step it with its action. A new episode draws from `new_keys`' chain where use_new_keys, else its own.

        The restarts run under one lax.cond: most steps restart no environment and skip making fresh episodes and
        selecting between whole states (a generated level per environment and step, for random levels)."""
        start = start | (carry.ended & ~hold)
        keep = hold & ~start
        chains = jax.vmap(jax.random.split)(jnp.where(use_new_keys[:, None], new_keys, carry.key))
        keys, subs = chains[:, 0], chains[:, 1]
        stepped, reward, terminated, truncated, info = jax.vmap(self.env.transition)(carry.state, actions,
                                                                                     carry.params)

        def restart(_):
            fresh = jax.vmap(self.env.initial_state)(subs)
            state = _select_rows(start, fresh, _select_rows(keep, carry.state, stepped))
            return state, _select_rows(start, jax.vmap(self._episode_params)(subs), carry.params)

        state, params = jax.lax.cond(jnp.any(start | keep), restart, lambda _: (stepped, carry.params), None)
        quiet = start | keep  # nothing happened: outputs of the episode's start, reward 0
        info = _select_rows(quiet, jax.vmap(_start_info)(state), info)
        terminated, truncated = terminated & ~quiet, truncated & ~quiet
        reward = jnp.where(quiet, 0.0, reward)
        ended = jnp.where(keep, carry.ended, terminated | truncated)
        carry = Carry(jnp.where(keep[:, None], carry.key, keys), state, params, ended)
        outputs = jax.vmap(lambda c, *rest: pack(self._outputs(c, *rest)).buffer)(carry, reward, terminated,
                                                                                  truncated, info)
        return carry, outputs

    # ------------------------------------------------------------ from Python

    def _call(self, actions, flags: tuple) -> tuple:
        """flags: (start, hold, new_keys, use_new_keys), placed on the device (shard_batch)."""
        if self.carry is None:  # an all-ended placeholder: the first call starts every episode
            self.carry = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), self._carry_shape)
        actions = shard_batch(jnp.asarray(actions), self.num_envs)
        self.carry, buffer = self._advance_jit(self.carry, actions, *flags)
        return host_rows(np.asarray(jax.device_get(buffer)), self.layout)

    def _flags(self, start, hold, new_keys, use_new_keys) -> tuple:
        return shard_batch(tuple(jnp.asarray(x) for x in (start, hold, new_keys, use_new_keys)), self.num_envs)

    def reset(self, keys: np.ndarray | None, mask: np.ndarray | None = None) -> tuple:
        """(obs, reward, terminated, truncated, info) as numpy arrays with a leading axis num_envs.

        keys: (N, 2) uint32 new key chains (seed_keys), or None to go on with each environment's own chain;
        mask: which environments to reset (None: all; the others keep their episode, and their outputs are those
        of a start: their observation, reward 0, neither flag).
        """
        n = self.num_envs
        if self.carry is None and (keys is None or (mask is not None and not np.all(mask))):
            raise RuntimeError("the first reset needs keys and resets every environment")
        mask = np.ones(n, bool) if mask is None else np.asarray(mask, bool)
        use_new = mask & (keys is not None)
        keys = np.zeros((n, 2), np.uint32) if keys is None else np.asarray(keys, np.uint32)
        return self._call(self._noop, self._flags(mask, ~mask, keys, use_new))

    def step(self, actions) -> tuple:
        """(obs, reward, terminated, truncated, info) of one step of every environment, numpy, leading axis N."""
        if self.carry is None:
            raise RuntimeError("step before reset: call reset() first")
        if self._step_flags is None:  # kept on the device: a step sends only its actions
            self._step_flags = self._flags(self._false, self._false, self._no_keys, self._false)
        return self._call(actions, self._step_flags)

    def levels(self):
        """The environments' current levels on the host (numpy leaves, leading axis N), for drawing."""
        if self.carry is None:
            raise RuntimeError("render before reset: call reset() first")
        return jax.device_get(self.carry.state.level)

    @property
    def devices(self) -> int:
        return batch_devices(self.num_envs)


def open_batch(level, num_envs: int, observation: str = "entity", action: str = "multi_discrete", *,
               pixel_resolution: int = 64, max_timesteps: int | None = None,
               dense_reward: float | None = None) -> Batch:
    """A Batch of the levels `level` names: a level file, a directory of level files, or random-s / random-m /
    random-l / random-all (kinetix.level_source, as `kinetix train --level`)."""
    from kinetix.level_source import RANDOM_LEVELS, level_source

    if level is None:
        raise ValueError(f"level is required: a level file, a directory of level files, or one of "
                         f"{', '.join(RANDOM_LEVELS)}")
    if not isinstance(level, str | os.PathLike):
        raise TypeError(f"level must be a path or one of {', '.join(RANDOM_LEVELS)}, got {type(level).__name__}")
    return Batch(level_source(level, dense_reward), num_envs, observation, action, pixel_resolution, max_timesteps)


def seed_keys(seed, num_envs: int, np_random: np.random.Generator) -> np.ndarray:
    """(num_envs, 2) uint32 key chains: split(PRNGKey(seed), num_envs) for an int seed; PRNGKey(seed_i) each for a
    sequence of num_envs seeds; from `np_random` (Gymnasium's generator of the env) for None."""
    if seed is None:
        seed = int(np_random.integers(0, 2**31 - 1))
    if isinstance(seed, list | tuple | np.ndarray):
        seeds = [int(s) for s in seed]
        if len(seeds) != num_envs:
            raise ValueError(f"seed: expected one int or {num_envs} ints, got {len(seeds)}")
        return np.stack([np.asarray(jax.random.PRNGKey(s)) for s in seeds])
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer):
        raise ValueError(f"seed must be an int, a list of ints or None, got {seed!r}")
    return np.asarray(jax.random.split(jax.random.PRNGKey(int(seed)), num_envs))
