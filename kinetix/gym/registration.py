"""The Gymnasium ids of kinetix.gym, registered when kinetix.gym is imported.

Gymnasium 1.x has no plugin entry points (it dropped them in 1.0); `gymnasium.make("kinetix.gym:kinetix/Level-v0")`
is its way of importing the registering module first.
"""

from __future__ import annotations

import gymnasium

ENV_ID = "kinetix/Level-v0"


def register_envs() -> None:
    """Register ENV_ID (once; importing kinetix.gym calls this). Both `gymnasium.make` and `gymnasium.make_vec` take
    the keyword arguments of kinetix.gym.KinetixGymEnv (`level=` is required); make_vec builds a KinetixVectorEnv."""
    if ENV_ID in gymnasium.registry:
        return
    # No max_episode_steps: the environment truncates at the level's own episode length.
    gymnasium.register(id=ENV_ID, entry_point="kinetix.gym.env:KinetixGymEnv",
                       vector_entry_point="kinetix.gym.vector:KinetixVectorEnv")
