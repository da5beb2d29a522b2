"""Environment wrappers.

LogWrapper (gymnax-style) keeps running episode statistics per environment. Every step's info gains
    returned_episode           bool: this step ended an episode (terminated or truncated)
    returned_episode_returns   float32: return of the last finished episode (this one if it just ended)
    returned_episode_lengths   int32: its length in agent steps
    returned_episode_solved    bool: whether it was solved
so a training loop averages the returned_* values where returned_episode is true.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from kinetix.env import EnvParams, EnvState, KinetixEnv


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LogState:
    env_state: EnvState
    episode_return: jax.Array  # float32, running
    episode_length: jax.Array  # int32, running
    returned_episode_return: jax.Array  # float32, of the last finished episode
    returned_episode_length: jax.Array  # int32
    returned_episode_solved: jax.Array  # bool


class LogWrapper:
    """Wraps a KinetixEnv (or another wrapper with the same API); other attributes pass through."""

    def __init__(self, env: KinetixEnv):
        self.env = env

    def __getattr__(self, name: str):
        return getattr(self.env, name)

    def reset(self, key: jax.Array, params: EnvParams | None = None):
        obs, env_state = self.env.reset(key, params)
        zero, count = jnp.asarray(0.0, jnp.float32), jnp.asarray(0, jnp.int32)
        return obs, LogState(env_state, zero, count, zero, count, jnp.asarray(False))

    def step(self, key: jax.Array, state: LogState, action, params: EnvParams | None = None):
        obs, env_state, reward, terminated, truncated, info = self.env.step(key, state.env_state, action, params)
        done = terminated | truncated
        episode_return = state.episode_return + reward
        episode_length = state.episode_length + 1
        new = LogState(
            env_state=env_state,
            episode_return=jnp.where(done, 0.0, episode_return).astype(jnp.float32),
            episode_length=jnp.where(done, 0, episode_length).astype(jnp.int32),
            returned_episode_return=jnp.where(done, episode_return, state.returned_episode_return).astype(jnp.float32),
            returned_episode_length=jnp.where(done, episode_length, state.returned_episode_length).astype(jnp.int32),
            returned_episode_solved=jnp.where(done, info["solved"], state.returned_episode_solved),
        )
        info = dict(info, returned_episode=done, returned_episode_returns=new.returned_episode_return,
                    returned_episode_lengths=new.returned_episode_length,
                    returned_episode_solved=new.returned_episode_solved)
        return obs, new, reward, terminated, truncated, info
