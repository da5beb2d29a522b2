"""`KinetixVectorEnv`: N environments as one `gymnasium.vector.VectorEnv`, stepped by one jitted batched call.

    envs = gymnasium.make_vec("kinetix/Level-v0", num_envs=512, level="levels/car_right.json")
    obs, info = envs.reset(seed=0)
    obs, reward, terminated, truncated, info = envs.step(envs.action_space.sample())

NumPy in and out; the state stays on the device (kinetix.gym.batch). Autoreset: Gymnasium's next-step mode
(metadata["autoreset_mode"] = AutoresetMode.NEXT_STEP): the step that ends an episode returns its last observation
with terminated or truncated set; the next step of that environment ignores its action and returns the first
observation of a new episode, with reward 0 and neither flag set. `reset(options={"reset_mask": mask})` resets only
the environments the boolean mask names.

info: for each of solved, failed, nan (bool), distance (float32), timestep and frozen (int32) an array of N values
and, as Gymnasium's vector envs do, a boolean array "_name" saying which environments have it (all of them).
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from kinetix.gym.batch import INFO_KEYS, open_batch, seed_keys
from kinetix.gym.render import DEFAULT_RENDER_SIZE, RENDER_MODES, check_render, frames, render_fps
from kinetix.gym.spaces import check_actions, to_gymnasium


class KinetixVectorEnv(gymnasium.vector.VectorEnv):
    """`num_envs` copies of a Kinetix environment (arguments as kinetix.gym.KinetixGymEnv)."""

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": RENDER_MODES, "render_fps": 30}

    def __init__(self, level=None, num_envs: int = 1, observation: str = "entity", action: str = "multi_discrete",
                 *, render_mode: str | None = None, render_size: int = DEFAULT_RENDER_SIZE,
                 pixel_resolution: int = 64, max_timesteps: int | None = None, dense_reward: float | None = None):
        check_render(render_mode, render_size)
        self._batch = open_batch(level, num_envs, observation, action, pixel_resolution=pixel_resolution,
                                 max_timesteps=max_timesteps, dense_reward=dense_reward)
        self.num_envs = num_envs
        self.single_observation_space = to_gymnasium(self._batch.env.observation_space)
        self.single_action_space = to_gymnasium(self._batch.env.action_space)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.render_mode = render_mode
        self.render_size = render_size
        self.metadata = {**self.metadata, "render_fps": render_fps(self._batch)}
        self._action_type = action
        self._all = np.ones(num_envs, bool)

    def reset(self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None):
        """New episodes. seed: an int (environment i's key chain starts at split(PRNGKey(seed), N)[i]), a list of N
        ints (PRNGKey(seed_i) each), or None (go on with each environment's chain; the first time, a seed from
        np_random). options: {"reset_mask": (N,) bool} to reset only those environments."""
        super().reset(seed=None if isinstance(seed, list | tuple) else seed)
        mask = None
        if options and "reset_mask" in options:
            mask = np.asarray(options["reset_mask"])
            if mask.shape != (self.num_envs,) or mask.dtype != np.bool_:
                raise ValueError(f"reset_mask must be a bool array of shape ({self.num_envs},), got {mask.dtype} "
                                 f"{mask.shape}")
        if options and set(options) - {"reset_mask"}:
            raise ValueError(f"unknown reset options {sorted(set(options) - {'reset_mask'})}; only reset_mask")
        keys = None if seed is None and self._batch.carry is not None else seed_keys(seed, self.num_envs,
                                                                                       self.np_random)
        obs, _, _, _, info = self._batch.reset(keys, mask)
        return obs, _vector_info(info)

    def step(self, actions):
        actions = check_actions(actions, self._action_type, (self.num_envs,))
        obs, reward, terminated, truncated, info = self._batch.step(actions)
        return obs, reward, terminated, truncated, _vector_info(info)

    def render(self) -> tuple[np.ndarray, ...] | None:
        """A (render_size, render_size, 3) uint8 frame per environment, drawn like the browser's."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; make the env with render_mode='rgb_array'")
            return None
        return frames(self._batch.levels(), range(self.num_envs), self.render_size)

    def close_extras(self, **kwargs: Any) -> None:
        self._batch.carry = None


def _vector_info(info: dict) -> dict:
    out = {}
    for name in INFO_KEYS:
        out[name] = info[name]
        out["_" + name] = np.ones(info[name].shape[0], bool)
    return out
