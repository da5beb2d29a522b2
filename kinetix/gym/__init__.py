"""Gymnasium interfaces for Kinetix levels (the optional extra: `pip install -e '.[gym]'`; docs/gymnasium.md).

    import gymnasium, kinetix.gym
    env = gymnasium.make("kinetix/Level-v0", level="levels/car_right.json")          # a gymnasium.Env
    envs = gymnasium.make_vec("kinetix/Level-v0", num_envs=512, level="random-s")    # a gymnasium.vector.VectorEnv

Importing this package registers the ids (kinetix.gym.registration); `gymnasium.make("kinetix.gym:kinetix/Level-v0",
...)` imports it by itself.
"""

from __future__ import annotations

try:
    import gymnasium  # noqa: F401
except ImportError as error:  # pragma: no cover - depends on the installation
    raise ImportError("kinetix.gym needs Gymnasium 1.x: pip install -e '.[gym]' (or pip install 'gymnasium>=1.4,<2')"
                      ) from error

from kinetix.gym.env import KinetixGymEnv
from kinetix.gym.registration import ENV_ID, register_envs
from kinetix.gym.vector import KinetixVectorEnv

register_envs()

__all__ = ["ENV_ID", "KinetixGymEnv", "KinetixVectorEnv", "register_envs"]
