"""The RL environment: a functional, gymnax-style API over levels of one size class.

    env = make_env(EnvConfig(size="s"), reset_single(level))
    params = EnvParams()
    obs, state = env.reset(key, params)
    obs, state, reward, terminated, truncated, info = env.step(key, state, action, params)

Everything is pure and jit/vmap-able: vmap over keys, states, actions and even params. `EnvConfig` is static
(changing it recompiles), `EnvParams` traced. `reset`, `step` and `step_no_reset` are jitted with the env static
(as gymnax does), so a Python loop of `env.step` compiles once per env; inside a caller's jit they are inlined.
Without it every eager call traced and compiled its physics scan afresh: seconds a step, and the compiled code
piled up until LLVM could map no more (the process aborted after ~40 steps at m).

One agent step
  1. the action becomes 4 motor and 2 thruster binding values (kinetix.actions), then per-joint and
     per-thruster actions through the level's bindings (kinetix.bindings.expand_actions);
  2. `frame_skip` physics steps run in a `lax.scan`; after each the goal is checked. Green touching red
     is a loss (-1), else green touching blue a win (+1): red wins ties. The first substep that wins or
     loses ends the episode and the scene is frozen there (later substeps are computed but discarded),
     so the returned state is the terminal scene itself;
  3. dense shaping adds dense_reward_scale * (last_distance - distance), `distance` being
     kinetix.goal.goal_distance after the step (nearest green-blue centres). `last_distance` is measured
     at reset, so the first step is shaped too and an episode's shaping sums to scale * (d_start - d_end).
     Shaping is off by default (scale 0): the public Kinetix used 0.1 in its env and 0.2 in its configs;
  4. terminated = won or lost; truncated = timestep >= max_timesteps and not terminated (kept apart,
     unlike the public Kinetix, so value bootstrapping can treat time limits correctly);
  5. a non-finite number anywhere in the scene (the engine guards against it; this is a second guard)
     ends the episode with reward 0 and info["nan"] = True, and the scene is rolled back to before the step.

`step` auto-resets: when the episode ends, the returned obs and state are those of a fresh level from the
reset function (drawn with the step's key), while reward, terminated, truncated and info describe the
transition that ended it. `step_no_reset` never resets (evaluation, the browser). info holds
`solved`, `failed`, `nan` (bool), `distance` (float32), `timestep` (int32, the step count of the episode
the transition belongs to, 1 on the first step) and `frozen` (int32, the bodies the engine's non-finite guard froze
over the transition's physics steps, jax2d.SimState.frozen; 0 in a healthy run).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

import jax2d
from jax2d.compact import Compact, layout_of, pack, unpack, update
from jax2d.state import SimParams, SolverConfig, empty_state
from kinetix import actions as actions_module
from kinetix import observations
from kinetix.actions import Box, DictSpace, Space
from kinetix.goal import goal_distance, touch_outcome
from kinetix.level import Level, LevelError, LevelFile, LevelParams, SizeClass, empty_level, make_level, size_class

ResetFn = Callable[[jax.Array], Level]


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """Compile-time settings (hashable). `size` accepts "s", "m", "l" or a SizeClass."""

    size: SizeClass | str
    observation: str = "entity"  # "entity" | "flat" | "pixels"
    action: str = "multi_discrete"  # "multi_discrete" | "discrete" | "continuous"
    frame_skip: int = 2  # physics steps per agent step
    pixel_resolution: int = 64
    solver: SolverConfig = SolverConfig()

    def __post_init__(self):
        object.__setattr__(self, "size", size_class(self.size))
        observations.check_observation_type(self.observation)
        actions_module.check_action_type(self.action)
        if isinstance(self.frame_skip, bool) or not isinstance(self.frame_skip, int) or self.frame_skip < 1:
            raise ValueError(f"frame_skip must be a positive integer, got {self.frame_skip!r}")
        if not isinstance(self.pixel_resolution, int) or self.pixel_resolution < 1:
            raise ValueError(f"pixel_resolution must be a positive integer, got {self.pixel_resolution!r}")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class EnvParams:
    """Runtime settings (traced: they may differ per batch element without recompiling)."""

    max_timesteps: int | jax.Array = 256
    dense_reward_scale: float | jax.Array = 0.0  # shaping off by default; see the module docstring
    sim: SimParams = dataclasses.field(default_factory=SimParams)  # physics, actuator scales included

    @classmethod
    def from_level_params(cls, level_params: LevelParams, **sim_overrides) -> EnvParams:
        """A level file's settings: episode length, shaping scale, time step and actuator scales.

        The level's frame_skip is compile-time: pass it to EnvConfig (see `EnvConfig(..., frame_skip=...)`).
        """
        return cls(max_timesteps=level_params.max_timesteps, dense_reward_scale=level_params.dense_reward_scale,
                   sim=level_params.sim_params(**sim_overrides))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class EnvState:
    level: Level  # the current scene, with roles and bindings
    timestep: jax.Array  # int32 agent steps taken in this episode
    last_distance: jax.Array  # float32 goal distance after the previous step (at reset: the initial one)


class StepOutput(NamedTuple):
    """What `step` returns, as one pytree (the packed form of `step_compact`)."""

    obs: Any
    state: EnvState
    reward: jax.Array
    terminated: jax.Array
    truncated: jax.Array
    info: dict


_NOT_A_STEP_OUTPUT = "previous must be what reset_compact or step_compact of this env returned"


_static_self = functools.partial(jax2d.jit, static_argnums=0)  # a method jitted per env (hashed by identity)


def _select(pred: jax.Array, on_true, on_false):
    """Tree-wise `pred ? on_true : on_false` for a scalar predicate (a per-element select under vmap)."""
    return jax.tree.map(lambda a, b: jnp.where(pred, a, b), on_true, on_false)


def all_finite(tree) -> jax.Array:
    """Whether every float in `tree` is finite, as one reduction: XLA's CPU runtime pays about half a
    microsecond per call for every reduction in a program, run or not, and one per leaf was 26 of them
    (docs/engine.md, "Reductions cost per call")."""
    leaves = [jnp.ravel(x) for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.floating)]
    return jnp.all(jnp.isfinite(jnp.concatenate(leaves))) if leaves else jnp.asarray(True)


@dataclasses.dataclass(frozen=True, eq=False)
class KinetixEnv:
    """The environment for one EnvConfig and one reset function. Build with `make_env`."""

    config: EnvConfig
    reset_fn: ResetFn

    # ------------------------------------------------------------ descriptions

    @property
    def default_params(self) -> EnvParams:
        return EnvParams()

    @property
    def action_space(self) -> Space:
        return actions_module.action_space(self.config.action)

    @property
    def num_actions(self) -> int:
        """Policy head size: 16 logits (multi_discrete), 11 (discrete) or 6 means (continuous)."""
        return actions_module.policy_outputs(self.config.action)

    @property
    def observation_space(self) -> Space:
        c = self.config
        if c.observation == "pixels":
            return Box(0.0, 1.0, (c.pixel_resolution, c.pixel_resolution, 3))

        level = empty_level(c.size)
        shapes = jax.eval_shape(lambda lv: observations.observe(lv, c.observation), level)
        clip = observations.OBS_CLIP

        def space(s):
            if s.dtype == jnp.bool_:
                return Box(0, 1, s.shape, jnp.dtype(bool))
            if jnp.issubdtype(s.dtype, jnp.integer):
                return Box(0, c.size.polygons + c.size.circles - 1, s.shape, s.dtype)
            return Box(-clip, clip, s.shape, s.dtype)

        if isinstance(shapes, dict):
            return DictSpace({name: space(s) for name, s in shapes.items()})
        return space(shapes)

    # ------------------------------------------------------------ the API

    def observe(self, state: EnvState):
        return observations.observe(state.level, self.config.observation, self.config.pixel_resolution)

    def initial_state(self, key: jax.Array, params: EnvParams | None = None) -> EnvState:
        """A fresh episode's state from the reset function (no observation computed)."""
        level = self.reset_fn(key)
        return EnvState(level=level, timestep=jnp.asarray(0, jnp.int32),
                        last_distance=goal_distance(level).astype(jnp.float32))

    @_static_self
    def reset(self, key: jax.Array, params: EnvParams | None = None):
        """(obs, state) of a fresh episode."""
        state = self.initial_state(key, params)
        return self.observe(state), state

    @_static_self
    def step_no_reset(self, key: jax.Array, state: EnvState, action, params: EnvParams | None = None):
        """(obs, state, reward, terminated, truncated, info) without auto-reset; `key` is unused (the physics is
        deterministic) and kept for a uniform signature."""
        next_state, reward, terminated, truncated, info = self.transition(state, action, params)
        return self.observe(next_state), next_state, reward, terminated, truncated, info

    @_static_self
    def step(self, key: jax.Array, state: EnvState, action, params: EnvParams | None = None):
        """(obs, state, reward, terminated, truncated, info); on episode end obs and state come from a reset."""
        next_state, reward, terminated, truncated, info = self.transition(state, action, params)
        with jax.named_scope("env_reset"):
            fresh = self.initial_state(key, params)
            next_state = _select(terminated | truncated, fresh, next_state)
        with jax.named_scope("env_observe"):
            obs = self.observe(next_state)
        return obs, next_state, reward, terminated, truncated, info

    # ------------------------------------------------------------ one scene from a Python loop

    def reset_compact(self, key: jax.Array, params: Compact) -> Compact:
        """`reset` as a packed StepOutput (reward 0, not ended, the info of the start): see `step_compact`."""
        obs, state = self.reset(key, unpack(params))
        false = jnp.asarray(False)
        info = {"solved": false, "failed": false, "nan": false, "distance": state.last_distance,
                "timestep": state.timestep, "frozen": jnp.zeros((), jnp.int32)}
        return pack(StepOutput(obs, state, jnp.asarray(0.0, jnp.float32), false, false, info))

    def step_compact(self, key: jax.Array, previous: Compact, action, params: Compact) -> Compact:
        """`step` for a Python loop at batch 1: one packed buffer in, one out (jax2d.compact).

        previous: what `reset_compact` or `step_compact` returned; params: `jax2d.compact.pack(params)`.
        JAX pays ~2 µs per argument and result leaf on every call, and a plain `step` passes 63 and
        returns 64 (~0.3 ms at any size). Read a result on the host with `jax2d.compact.unpack_host`,
        which gives a StepOutput of numpy arrays. Equal to `step`, bitwise.
        """
        before = unpack(previous)
        if not isinstance(before, StepOutput):
            raise ValueError(_NOT_A_STEP_OUTPUT)
        params = unpack(params)
        next_state, reward, terminated, truncated, info = self.transition(before.state, action, params)
        # The state works on packed words: its leaves are contiguous in the packed StepOutput, a step
        # rewrites only the leaves the physics changed (jax2d.compact.update), and the auto-reset is one
        # select over the words instead of one per leaf. Selecting bits equals selecting values.
        start = previous.layout.offsets[len(jax.tree.leaves(before.obs))]
        state_layout = layout_of(before.state)
        words = previous.buffer[start:start + state_layout.size]
        stepped = update(Compact(words, state_layout), before.state, next_state).buffer
        fresh = pack(self.initial_state(key, params)).buffer
        words = jnp.where(terminated | truncated, fresh, stepped)
        state = unpack(Compact(words, state_layout))
        obs = self.observe(state)
        layout = layout_of(StepOutput(obs, state, reward, terminated, truncated, info))
        if layout != previous.layout:
            raise ValueError(_NOT_A_STEP_OUTPUT)
        head, tail = pack(obs).buffer, pack((reward, terminated, truncated, info)).buffer
        return Compact(jnp.concatenate([head, words, tail]), layout)

    def transition(self, state: EnvState, action, params: EnvParams | None = None):
        """(next_state, reward, terminated, truncated, info): one agent step, no observation, no reset."""
        params = self.default_params if params is None else params
        level = state.level
        with jax.named_scope("env_actions"):
            motor, thrust = actions_module.level_actions(level, action, self.config.action)

        def physics_step(carry, _):
            sim, ended, won, lost, frozen = carry
            with jax.named_scope("env_physics"):
                new_sim = jax2d.step(sim, params.sim, motor, thrust, self.config.solver)
            with jax.named_scope("env_goal"):
                after = dataclasses.replace(level, sim=new_sim)
                blue, lose = touch_outcome(after)
                win = blue & ~lose  # losing dominates a simultaneous win
                won, lost = won | (~ended & win), lost | (~ended & lose)
                frozen = frozen + jnp.where(ended, 0, new_sim.frozen)
            with jax.named_scope("env_freeze"):
                sim = _select(ended, sim, new_sim)  # frozen from the first terminating substep on
            return (sim, ended | win | lose, won, lost, frozen), None

        false = jnp.asarray(False)
        zero = jnp.zeros((), jnp.int32)
        (sim, _, won, lost, frozen), _ = jax.lax.scan(physics_step, (level.sim, false, false, false, zero), None,
                                                      length=self.config.frame_skip)
        with jax.named_scope("env_finite"):
            finite = all_finite(sim)
            next_level = _select(finite, dataclasses.replace(level, sim=sim), level)  # roll back a non-finite step
        won, lost = won & finite, lost & finite

        with jax.named_scope("env_distance"):
            distance = goal_distance(next_level).astype(jnp.float32)
        shaping = jnp.asarray(params.dense_reward_scale, jnp.float32) * (state.last_distance - distance)
        sparse = jnp.where(won, 1.0, 0.0) - jnp.where(lost, 1.0, 0.0)
        reward = jnp.where(finite, sparse + jnp.nan_to_num(shaping), 0.0).astype(jnp.float32)

        timestep = state.timestep + 1
        terminated = won | lost | ~finite
        truncated = (timestep >= params.max_timesteps) & ~terminated
        next_state = EnvState(level=next_level, timestep=timestep, last_distance=distance)
        info = {"solved": won, "failed": lost, "nan": ~finite, "distance": distance, "timestep": timestep,
                "frozen": frozen}
        return next_state, reward, terminated, truncated, info


def make_env(config: EnvConfig, reset_fn: ResetFn | Level | LevelFile) -> KinetixEnv:
    """The environment for `config`; `reset_fn(key) -> Level` (see kinetix.reset_fns), or one level to always reset to.

    Checks once, by shape and dtype, that the reset function gives levels of the config's size class.
    """
    if isinstance(reset_fn, Level | LevelFile):
        from kinetix.reset_fns import reset_single

        reset_fn = reset_single(reset_fn)
    if not callable(reset_fn):
        raise TypeError(f"reset_fn must be a callable key -> Level, a Level or a LevelFile, got {type(reset_fn)}")
    level = jax.eval_shape(reset_fn, jax.random.PRNGKey(0))
    if not isinstance(level, Level):
        raise TypeError(f"reset_fn must return a Level, got {type(level).__name__}")
    if level.sim.bodies.active.ndim != 1:
        raise LevelError(f"reset_fn must return one level, got a batch of shape {level.sim.bodies.active.shape[:-1]}")
    if level.capacity != config.size.capacity:
        raise LevelError(f"reset_fn gives levels of capacity {level.capacity}, but the config's size "
                         f"{config.size.name} has {config.size.capacity}; use kinetix.levels.resize")
    # Dtypes matter as much as shapes: an int32 `active` still selects, but ~active is no longer a mask.
    with jax.ensure_compile_time_eval():  # concrete even when make_env is called inside a trace
        want = make_level(empty_state(config.size.capacity))  # no walls: any custom size class has these dtypes
    wrong = [f"{jax.tree_util.keystr(path)} is {got.dtype}, not {expected.dtype}" for (path, got), expected
             in zip(jax.tree_util.tree_flatten_with_path(level)[0], jax.tree.leaves(want), strict=True)
             if got.dtype != expected.dtype]
    if wrong:
        raise LevelError(f"reset_fn gives levels with the wrong dtypes: {'; '.join(wrong[:3])}")
    return KinetixEnv(config, reset_fn)
