"""Action distributions over the network's head outputs, for each action type (see kinetix.actions).

    multi_discrete  16 logits split (3, 3, 3, 3, 2, 2): independent categoricals, log-probs and entropies summed
    discrete        11 logits: one categorical
    continuous      6 means + 6 log stds: a diagonal Gaussian (the env clips the sample to the action bounds)
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp

from kinetix.actions import NUM_BINDINGS, action_space, check_action_type


def _splits(action_type: str) -> list[int]:
    return list(itertools.accumulate(action_space(action_type).nvec))[:-1]


def sample(key: jax.Array, outputs: jax.Array, action_type: str) -> jax.Array:
    """One action per row of `outputs` (leading batch axes allowed)."""
    action_type = check_action_type(action_type)
    if action_type == "multi_discrete":
        parts = jnp.split(outputs, _splits(action_type), axis=-1)
        keys = jax.random.split(key, len(parts))
        return jnp.stack([jax.random.categorical(k, p) for k, p in zip(keys, parts, strict=True)], -1).astype(jnp.int32)
    if action_type == "discrete":
        return jax.random.categorical(key, outputs).astype(jnp.int32)
    mean, log_std = outputs[..., :NUM_BINDINGS], outputs[..., NUM_BINDINGS:]
    return mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)


def mode(outputs: jax.Array, action_type: str) -> jax.Array:
    """The most likely action (greedy evaluation)."""
    action_type = check_action_type(action_type)
    if action_type == "multi_discrete":
        parts = jnp.split(outputs, _splits(action_type), axis=-1)
        return jnp.stack([p.argmax(-1) for p in parts], -1).astype(jnp.int32)
    if action_type == "discrete":
        return outputs.argmax(-1).astype(jnp.int32)
    return outputs[..., :NUM_BINDINGS]


def log_prob(outputs: jax.Array, action: jax.Array, action_type: str) -> jax.Array:
    action_type = check_action_type(action_type)
    if action_type == "multi_discrete":
        parts = jnp.split(outputs, _splits(action_type), axis=-1)
        total = 0.0
        for i, p in enumerate(parts):
            logp = jax.nn.log_softmax(p)
            total = total + jnp.take_along_axis(logp, action[..., i:i + 1].astype(jnp.int32), -1)[..., 0]
        return total
    if action_type == "discrete":
        logp = jax.nn.log_softmax(outputs)
        return jnp.take_along_axis(logp, action[..., None].astype(jnp.int32), -1)[..., 0]
    mean, log_std = outputs[..., :NUM_BINDINGS], outputs[..., NUM_BINDINGS:]
    z = (action - mean) / jnp.exp(log_std)
    return jnp.sum(-0.5 * z ** 2 - log_std - 0.5 * jnp.log(2 * jnp.pi), -1)


def _categorical_entropy(logits: jax.Array) -> jax.Array:
    logp = jax.nn.log_softmax(logits)
    return -jnp.sum(jnp.exp(logp) * logp, -1)


def binding_entropies(outputs: jax.Array) -> jax.Array:
    """(..., 6): the entropy of each binding's categorical, from multi_discrete outputs (..., 16)."""
    parts = jnp.split(outputs, _splits("multi_discrete"), axis=-1)
    return jnp.stack([_categorical_entropy(p) for p in parts], -1)


def entropy(outputs: jax.Array, action_type: str) -> jax.Array:
    action_type = check_action_type(action_type)
    if action_type == "multi_discrete":
        parts = jnp.split(outputs, _splits(action_type), axis=-1)
        return sum(_categorical_entropy(p) for p in parts)  # in this order, as training always summed it
    if action_type == "discrete":
        return _categorical_entropy(outputs)
    log_std = outputs[..., NUM_BINDINGS:]
    return jnp.sum(log_std + 0.5 * jnp.log(2 * jnp.pi * jnp.e), -1)
