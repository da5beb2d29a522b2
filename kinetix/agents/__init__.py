"""Agents: PPO training, curricula, checkpoints, evaluation and `load_policy` (the interface the server and the
recorder use). See docs/agents.md.

    from kinetix.agents import load_policy
    policy = load_policy("general", env)          # or "noop", "random", a checkpoint directory
    action, value = jax2d.jit(policy.act)(key, obs)

Importing this package is cheap; the modules (flax, optax) load on first use of a name.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from kinetix.agents.evaluate import evaluate
    from kinetix.agents.policy import Policy, load_policy
    from kinetix.agents.train import train_agent

__all__ = ["Policy", "load_policy", "train_agent", "evaluate"]

_LAZY = {"Policy": "kinetix.agents.policy", "load_policy": "kinetix.agents.policy",
         "train_agent": "kinetix.agents.train", "evaluate": "kinetix.agents.evaluate"}


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'kinetix.agents' has no attribute {name!r}")
