"""Whole episodes on a batch of levels, for evaluation and for the sfl curriculum. Pure and jittable."""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from kinetix.env import EnvParams, EnvState, KinetixEnv
from kinetix.goal import goal_distance
from kinetix.level import Level


def fresh_state(level: Level) -> EnvState:
    """The state an episode on `level` starts from (what KinetixEnv.initial_state builds, without a reset_fn)."""
    return EnvState(level=level, timestep=jnp.asarray(0, jnp.int32),
                    last_distance=goal_distance(level).astype(jnp.float32))


def keep_finished(done: jax.Array, state: EnvState, next_state: EnvState) -> EnvState:
    """`next_state`, but `state` for the episodes already `done` (B,): a finished scene stays frozen, so later
    steps of a batch that runs on change nothing in it."""
    return jax.tree.map(lambda a, b: jnp.where(done.reshape(done.shape + (1,) * (a.ndim - 1)), a, b),
                        state, next_state)


def run_episodes(env: KinetixEnv, env_params: EnvParams, act: Callable, levels: Level, key: jax.Array,
                 num_steps: int) -> tuple[jax.Array, jax.Array]:
    """(solved (B,) bool, return (B,) float32) of one episode per level of the batch `levels`.

    `act(key, obs) -> action` acts on ONE observation. `env_params` may be batched like `levels` (leading axis)
    or shared. Episodes run for `num_steps` agent steps (use the longest max_timesteps); a finished episode
    stops counting (the env is not reset)."""
    batch = levels.sim.bodies.active.shape[0]
    params_axis = 0 if jnp.ndim(env_params.max_timesteps) == 1 else None
    step = jax.vmap(env.step_no_reset, in_axes=(None, 0, 0, params_axis))

    def one_step(carry, step_key):
        state, obs, done, solved, total = carry
        action = jax.vmap(act)(jax.random.split(step_key, batch), obs)
        obs, next_state, reward, terminated, truncated, info = step(step_key, state, action, env_params)
        total = total + jnp.where(done, 0.0, reward)
        solved = solved | (~done & info["solved"])
        state = keep_finished(done, state, next_state)
        return (state, obs, done | terminated | truncated, solved, total), None

    state = jax.vmap(fresh_state)(levels)
    obs = jax.vmap(env.observe)(state)
    false = jnp.zeros((batch,), bool)
    init = (state, obs, false, false, jnp.zeros((batch,), jnp.float32))
    (_, _, _, solved, total), _ = jax.lax.scan(one_step, init, jax.random.split(key, num_steps))
    return solved, total
