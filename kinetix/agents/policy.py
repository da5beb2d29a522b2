"""`load_policy(spec, env) -> Policy`: what plays a level, for eval, recording and the server.

    spec  "noop"     the no-op action every step (value 0)
          "random"   uniformly random actions of the env's action space (value 0)
          "general"  the general agent shipped in kinetix/agents/general/
          a path     a checkpoint directory written by `kinetix train`

`Policy.act(key, obs) -> (action, value)` takes ONE observation of `env` (no batch axis) and is jittable
(`jax2d.jit(policy.act)`, vmap it for batches). Checkpoint policies sample from the policy distribution unless
`deterministic=True` (then the most likely action).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp

from kinetix import actions
from kinetix.agents import checkpoint as checkpoint_module
from kinetix.agents import distributions
from kinetix.agents.checkpoint import CheckpointError
from kinetix.agents.networks import ActorCritic
from kinetix.agents.ppo import make_network
from kinetix.env import KinetixEnv

GENERAL_DIR = Path(__file__).resolve().parent / "general"
# Specialists shipped for the project's own levels, one checkpoint per level stem (server.agents.project).
SPECIALISTS_DIR = Path(__file__).resolve().parent / "specialists"
BUILTIN = ("noop", "random", "general")


@dataclasses.dataclass(frozen=True, eq=False)
class Policy:
    name: str
    action_type: str
    observation: str | None  # the observation type it needs (None: any)
    _apply: Callable[[object, jax.Array, object], tuple[jax.Array, jax.Array]]
    params: object = None  # the network parameters (None for noop and random)
    # Equal for policies whose `apply` is the same computation (same network shape, action space and sampling):
    # a server jits `apply(params, key, obs)` once per signature and passes each agent's params as an argument.
    signature: tuple = ()

    def act(self, key: jax.Array, obs) -> tuple[jax.Array, jax.Array]:
        """(action, value estimate) for one observation."""
        return self._apply(self.params, key, obs)

    def apply(self, params, key: jax.Array, obs) -> tuple[jax.Array, jax.Array]:
        """`act` with the parameters as an argument (jit this to share one compile between agents)."""
        return self._apply(params, key, obs)


def resolve(spec: str) -> str | Path:
    """"noop" / "random" stay names; "general" and paths become checkpoint directories."""
    if spec in ("noop", "random"):
        return spec
    if spec == "general":
        if not (GENERAL_DIR / checkpoint_module.CONFIG_FILE).is_file():
            raise CheckpointError(f"the general agent is not in this checkout ({GENERAL_DIR} has no checkpoint)")
        return GENERAL_DIR
    path = Path(os.path.expanduser(spec))
    if not path.exists():
        raise CheckpointError(f"unknown agent {spec!r}: use noop, random, general or a checkpoint directory")
    return path


def required_observation(spec: str) -> str | None:
    """The observation type an agent needs (None for noop and random), without building anything."""
    where = resolve(spec)
    return None if isinstance(where, str) else checkpoint_module.load(where).env["observation"]


def load_network(where: str | os.PathLike, env: KinetixEnv, spec: str | None = None) -> tuple[ActorCritic, object]:
    """(network, parameters) of the checkpoint directory `where`, checked against `env`'s observation and action
    space. `network.apply({"params": params}, obs_batch)` gives (head outputs, values); kinetix.agents.distributions
    reads the outputs. `spec`: how the user named the agent, for error messages."""
    spec = str(where) if spec is None else spec
    action_type = env.config.action
    ckpt = checkpoint_module.load(where)
    need = ckpt.env
    if need["observation"] != env.config.observation:
        raise CheckpointError(f"agent {spec} was trained on {need['observation']!r} observations but the env gives "
                              f"{env.config.observation!r}; make the env with EnvConfig(observation="
                              f"{need['observation']!r})")
    if need["action"] != action_type:
        raise CheckpointError(f"agent {spec} acts in the {need['action']!r} space but the env uses {action_type!r}")
    if need["observation"] != "entity" and need["size"] != env.config.size.name:
        raise CheckpointError(f"agent {spec} ({need['observation']} observations) only fits size {need['size']}, "
                              f"the env is size {env.config.size.name}")
    if need["observation"] == "pixels" and need["pixel_resolution"] != env.config.pixel_resolution:
        raise CheckpointError(f"agent {spec} needs pixel_resolution {need['pixel_resolution']}")
    tc = ckpt.train_config
    network = make_network(tc, action_type)
    return network, jax.tree.map(jnp.asarray, ckpt.params)


def load_policy(spec: str, env: KinetixEnv, deterministic: bool = False) -> Policy:
    action_type = env.config.action
    where = resolve(spec)
    zero = jnp.asarray(0.0, jnp.float32)
    if where == "noop":
        action = actions.noop_action(action_type)
        return Policy("noop", action_type, None, lambda params, key, obs: (action, zero),
                      signature=("noop", action_type))
    if where == "random":
        return Policy("random", action_type, None,
                      lambda params, key, obs: (actions.sample_random_action(key, action_type), zero),
                      signature=("random", action_type))
    network, params = load_network(where, env, spec)
    observation = env.config.observation  # load_network checked it is the checkpoint's

    def apply(net_params, key, obs):
        batched = jax.tree.map(lambda x: jnp.asarray(x)[None], obs)
        outputs, value = network.apply({"params": net_params}, batched)
        action = (distributions.mode(outputs, action_type) if deterministic
                  else distributions.sample(key, outputs, action_type))
        return action[0], value[0]

    name = "general" if spec == "general" else str(where)
    signature = ("network", network.network, network.width, network.hidden, action_type, observation, deterministic)
    return Policy(name, action_type, observation, apply, params, signature)
