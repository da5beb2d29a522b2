"""The shipped general agent: present, small enough, documented with its command, and loadable on every size."""

import json

import jax
import jax.numpy as jnp
import numpy as np

import jax2d
from kinetix.agents.policy import GENERAL_DIR, load_policy
from kinetix.env import EnvConfig, make_env
from kinetix.level import empty_level

MAX_BYTES = 20 * 1024 * 1024


def test_general_agent_is_shipped_with_its_command():
    files = [p for p in GENERAL_DIR.rglob("*") if p.is_file()]
    assert sum(p.stat().st_size for p in files) <= MAX_BYTES
    readme = (GENERAL_DIR / "README.md").read_text()
    config = json.loads((GENERAL_DIR / "config.json").read_text())
    assert config["info"]["command"].startswith("kinetix train ")
    assert config["info"]["command"] in readme  # the README states the exact command that produced it


def test_general_agent_acts_on_every_size():
    for size in ("s", "m", "l"):
        env = make_env(EnvConfig(size), empty_level(size))
        obs, _ = env.reset(jax.random.key(0))
        action, value = jax2d.jit(load_policy("general", env).act)(jax.random.key(1), obs)
        assert env.action_space.contains(np.asarray(action)) and bool(jnp.isfinite(value))
