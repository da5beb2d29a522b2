"""`KinetixGymEnv`: one environment as a `gymnasium.Env`, registered as "kinetix/Level-v0".

    env = gymnasium.make("kinetix/Level-v0", level="levels/car_right.json")   # or a directory, or "random-s"
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())

terminated: the episode was won (green touched blue: reward +1) or lost (green touched red: -1), or the physics went
non-finite (info["nan"]); truncated: the level's episode length ran out without that. The environment does not
reset itself: after either, call reset(). It is environment 0 of a kinetix.gym.batch.Batch of one, so its episodes
for a seed are those of environment 0 of `KinetixVectorEnv(..., num_envs=1)` for that seed.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np

from kinetix.gym.batch import INFO_KEYS, open_batch, seed_keys
from kinetix.gym.render import DEFAULT_RENDER_SIZE, RENDER_MODES, check_render, frames, render_fps
from kinetix.gym.spaces import check_actions, to_gymnasium


class KinetixGymEnv(gymnasium.Env):
    """A Kinetix level (or levels) as a Gymnasium environment.

    level: a level file (either format), a directory of *.json level files (one drawn per episode), or random-s /
    random-m / random-l / random-all (a generated level per episode; random-all: s, m or l, padded to l).
    observation: "entity" (a Dict), "flat" or "pixels";
    action: "multi_discrete", "discrete" or "continuous". max_timesteps / dense_reward: override the level's
    episode length and shaping scale. render_mode "rgb_array": render() returns a (render_size, render_size, 3)
    uint8 frame drawn like the browser's.
    """

    metadata = {"render_modes": RENDER_MODES, "render_fps": 30}

    def __init__(self, level=None, observation: str = "entity", action: str = "multi_discrete", *,
                 render_mode: str | None = None, render_size: int = DEFAULT_RENDER_SIZE, pixel_resolution: int = 64,
                 max_timesteps: int | None = None, dense_reward: float | None = None):
        check_render(render_mode, render_size)
        self._batch = open_batch(level, 1, observation, action, pixel_resolution=pixel_resolution,
                                 max_timesteps=max_timesteps, dense_reward=dense_reward)
        self.observation_space = to_gymnasium(self._batch.env.observation_space)
        self.action_space = to_gymnasium(self._batch.env.action_space)
        self.render_mode = render_mode
        self.render_size = render_size
        self.metadata = {**self.metadata, "render_fps": render_fps(self._batch)}
        self._action_type = action
        self._ended = True  # no episode yet

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """A new episode. With a seed, its key chain restarts from the seed; without, it goes on from the last
        episode's (or from Gymnasium's np_random on the first reset)."""
        super().reset(seed=seed)
        if seed is not None or self._batch.carry is None:
            rows = self._batch.reset(seed_keys(seed, 1, self.np_random))
        else:
            rows = self._batch.reset(None, np.ones(1, bool))
        self._ended = False
        obs, _, _, _, info = rows
        return _first(obs), _first(info)

    def step(self, action):
        if self._ended:
            raise RuntimeError("the episode has ended (or was never started): call reset() before step()")
        actions = check_actions(action, self._action_type, ())[None]
        obs, reward, terminated, truncated, info = self._batch.step(actions)
        terminated, truncated = bool(terminated[0]), bool(truncated[0])
        self._ended = terminated or truncated
        return _first(obs), float(reward[0]), terminated, truncated, _first(info)

    def render(self):
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; make the env with render_mode='rgb_array'")
            return None
        return frames(self._batch.levels(), [0], self.render_size)[0]

    def close(self):
        self._batch.carry = None
        super().close()


def _first(tree):
    """Environment 0 of a batch of one (host arrays): arrays lose the batch axis, info values become scalars."""
    if isinstance(tree, dict) and set(tree) == set(INFO_KEYS):
        return {name: tree[name][0] for name in INFO_KEYS}
    if isinstance(tree, dict):
        return {name: value[0] for name, value in tree.items()}
    return tree[0]
