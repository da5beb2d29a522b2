"""Actor-critic networks (flax.linen) for the three observation types.

    entity (default)  permutation-invariant over the symbolic_entity observation: one encoder MLP per entity kind
                      (polygons, circles, joint rows, thrusters); joint and thruster rows also see the embeddings of
                      the bodies they attach to (gathered by joint_indexes / thruster_indexes), so the network knows
                      which body a motor turns. One masked self-attention layer mixes all entities, then masked mean
                      and max pooling give a fixed-size summary. Nothing depends on slot order or slot count, so one
                      network runs on every size class.
    flat              an MLP over the flat vector (size-class specific).
    pixels            a small CNN.

Every network returns (head outputs, value): logits (multi_discrete 16, discrete 11) or, for continuous actions,
6 means followed by 6 log standard deviations (a learned, state-independent parameter); see
kinetix.agents.distributions.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from kinetix.actions import policy_outputs

NETWORK_TYPES = ("entity", "flat", "pixels")


def _mlp(x: jax.Array, sizes: tuple[int, ...], final_activation: bool = True) -> jax.Array:
    for i, size in enumerate(sizes):
        x = nn.Dense(size)(x)
        if final_activation or i < len(sizes) - 1:
            x = nn.relu(x)
    return x


class Heads(nn.Module):
    """Separate actor and critic MLPs on a shared embedding (separate trunks keep the value loss from
    dominating the policy features, as in PureJaxRL's separate networks)."""

    num_outputs: int
    hidden: int = 128

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        actor = _mlp(x, (self.hidden, self.hidden))
        out = nn.Dense(self.num_outputs, kernel_init=nn.initializers.orthogonal(0.01))(actor)
        critic = _mlp(x, (self.hidden, self.hidden))
        value = nn.Dense(1, kernel_init=nn.initializers.orthogonal(1.0))(critic)[..., 0]
        return out, value


def _masked_pool(tokens: jax.Array, mask: jax.Array) -> jax.Array:
    """Mean and max over the entity axis (-2) of the active tokens; zero if none is active."""
    m = mask[..., None].astype(tokens.dtype)
    count = jnp.maximum(m.sum(-2), 1.0)
    mean = (tokens * m).sum(-2) / count
    maxed = jnp.where(mask[..., None], tokens, -1e9).max(-2)
    maxed = jnp.where(mask.any(-1, keepdims=True), maxed, 0.0)
    return jnp.concatenate([mean, maxed], axis=-1)


class EntityEncoder(nn.Module):
    """One observation dict (unbatched) -> embedding. vmap it over a batch."""

    width: int = 64
    heads: int = 4

    @nn.compact
    def __call__(self, obs: dict) -> jax.Array:
        w = self.width
        polygons = _mlp(obs["polygons"], (w, w))
        circles = _mlp(obs["circles"], (w, w))
        bodies = jnp.concatenate([polygons, circles], axis=0)  # global body index order
        body_mask = jnp.concatenate([obs["polygon_mask"], obs["circle_mask"]])
        ji = obs["joint_indexes"]
        joints = _mlp(jnp.concatenate([obs["joints"], bodies[ji[:, 0]], bodies[ji[:, 1]]], axis=-1), (w, w))
        thrusters = _mlp(jnp.concatenate([obs["thrusters"], bodies[obs["thruster_indexes"]]], axis=-1), (w, w))
        tokens = jnp.concatenate([bodies, joints, thrusters], axis=0)
        mask = jnp.concatenate([body_mask, obs["joint_mask"], obs["thruster_mask"]])
        # every token may attend to every active token; inactive query rows attend to all so softmax stays finite
        attend = mask[None, :] | ~mask[:, None]
        mixed = nn.MultiHeadDotProductAttention(num_heads=self.heads, qkv_features=w)(
            nn.LayerNorm()(tokens), mask=attend[None])
        tokens = tokens + mixed
        tokens = tokens + _mlp(nn.LayerNorm()(tokens), (w, w), final_activation=False)
        return _masked_pool(tokens, mask)


class ActorCritic(nn.Module):
    """obs (batched: a leading axis) -> (logits or means, value)."""

    network: str = "entity"
    action: str = "multi_discrete"
    width: int = 64
    hidden: int = 128

    @nn.compact
    def __call__(self, obs) -> tuple[jax.Array, jax.Array]:
        if self.network == "entity":
            features = nn.vmap(EntityEncoder, variable_axes={"params": None}, split_rngs={"params": False})(
                width=self.width)(obs)
        elif self.network == "flat":
            features = _mlp(obs, (self.hidden, self.hidden))
        elif self.network == "pixels":
            x = obs
            for channels, stride in ((16, 2), (32, 2), (32, 2)):
                x = nn.relu(nn.Conv(channels, (3, 3), strides=(stride, stride))(x))
            features = _mlp(x.reshape(x.shape[0], -1), (self.hidden,))
        else:
            raise ValueError(f"unknown network {self.network!r}: use one of {', '.join(NETWORK_TYPES)}")
        outputs, value = Heads(policy_outputs(self.action), self.hidden)(features)
        if self.action == "continuous":  # a state-independent log std, appended to the means
            log_std = self.param("log_std", nn.initializers.constant(-0.5), (outputs.shape[-1],))
            outputs = jnp.concatenate([outputs, jnp.broadcast_to(log_std, outputs.shape)], axis=-1)
        return outputs, value
