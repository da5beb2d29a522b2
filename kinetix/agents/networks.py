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

Hidden layers use `activation`: tanh (the default) or relu. A relu unit whose pre-activation is negative on every
input gets no gradient again and is dead for good. The first general run's actor lost all 128 units of its second
hidden layer that way (dead on every state by 109M env steps, 44 % of them at 65M): its policy became one fixed
distribution, the same on every level, that the entropy bonus then pulled to uniform (kinetix.agents.health
measures it). A tanh unit always passes some gradient. Checkpoints from before the choice existed are relu
(ppo.LEGACY_ACTIVATION). Each hidden layer sows its pre-activation into the "intermediates" collection under a name
saying what it is (actor_0, critic_1, polygons_0, ...), only collected when asked for: kinetix.agents.health reads
every layer, and training reports the heads' dead share per update (dead_share, ppo_loss).

`pooled_norm` (entity network; the default for new networks) puts a LayerNorm on the pooled summary before the
heads. Without it the summary is the unnormalised residual stream of the attention layer, and it grows as training
goes on: in the tanh run kinetix/agents/general/sfl-tanh the pooled features' rms on levels/ went 1.3, 1.7, 2.5 at
5.8M, 11.5M and 22.7M env steps, the mean |pre-activation| of the heads' first layers 1.5-1.9, 2.2-2.8, 4.2-4.4,
so those tanh units saturated (live share 0.58, a growing share of critic units dead in training). A normalised
summary keeps the heads' inputs at unit scale whatever the encoder's weights do (the final LayerNorm of a
pre-norm transformer). The flat and pixel networks pool nothing and ignore it. Networks saved before the field
existed have none (ppo.LEGACY_FIELDS).
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from kinetix.actions import policy_outputs

NETWORK_TYPES = ("entity", "flat", "pixels")
ACTIVATIONS = {"tanh": nn.tanh, "relu": nn.relu}
DEAD_SLOPE = 1e-3  # below this slope a hidden unit passes (next to) no gradient: dead on that input


def check_activation(activation: str) -> str:
    if activation not in ACTIVATIONS:
        raise ValueError(f"unknown activation {activation!r}: use one of {', '.join(ACTIVATIONS)}")
    return activation


def slope(activation: str, pre: jax.Array) -> jax.Array:
    """The activation's derivative at the pre-activations `pre`."""
    if activation == "relu":
        return (pre > 0).astype(pre.dtype)
    return 1.0 - jnp.tanh(pre) ** 2


def pre_activations(intermediates: dict) -> dict[str, jax.Array]:
    """{label: pre-activation} from a network's "intermediates" collection (each sown value is a 1-tuple)."""
    found = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(intermediates)[0]:
        label = next(p.key for p in reversed(path) if isinstance(p, jax.tree_util.DictKey))
        found[label] = leaf
    return found


def dead_share(intermediates: dict, activation: str, head: str) -> jax.Array:
    """The share of dead units (slope below DEAD_SLOPE on every row of the batch) in the most dead hidden layer of
    `head` ("actor" or "critic"): 1.0 once one whole layer is dead, when that head's output no longer depends on its
    input. Its rows are samples, so no padding is counted."""
    shares = [(slope(activation, pre) < DEAD_SLOPE).all(axis=tuple(range(pre.ndim - 1))).mean()
              for label, pre in sorted(pre_activations(intermediates).items())
              if label.rsplit("_", 1)[0] == head]
    return jnp.max(jnp.stack(shares))


def _hidden(module: nn.Module, x: jax.Array, activation: str, label: str) -> jax.Array:
    """One hidden layer's nonlinearity; its input is sown as intermediates[label] (see the module docstring)."""
    module.sow("intermediates", label, x)
    return ACTIVATIONS[activation](x)


def _mlp(module: nn.Module, x: jax.Array, sizes: tuple[int, ...], activation: str, label: str,
         final_activation: bool = True) -> jax.Array:
    """Dense layers of `sizes`, created in `module`; hidden layer i's pre-activation is sown as f"{label}_{i}"."""
    for i, size in enumerate(sizes):
        x = nn.Dense(size)(x)
        if final_activation or i < len(sizes) - 1:
            x = _hidden(module, x, activation, f"{label}_{i}")
    return x


class Heads(nn.Module):
    """Separate actor and critic MLPs on a shared embedding (separate trunks keep the value loss from
    dominating the policy features, as in PureJaxRL's separate networks)."""

    num_outputs: int
    hidden: int = 128
    activation: str = "tanh"

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        actor = _mlp(self, x, (self.hidden, self.hidden), self.activation, "actor")
        out = nn.Dense(self.num_outputs, kernel_init=nn.initializers.orthogonal(0.01))(actor)
        critic = _mlp(self, x, (self.hidden, self.hidden), self.activation, "critic")
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
    activation: str = "tanh"
    pooled_norm: bool = True

    @nn.compact
    def __call__(self, obs: dict) -> jax.Array:
        w, act = self.width, self.activation
        polygons = _mlp(self, obs["polygons"], (w, w), act, "polygons")
        circles = _mlp(self, obs["circles"], (w, w), act, "circles")
        bodies = jnp.concatenate([polygons, circles], axis=0)  # global body index order
        body_mask = jnp.concatenate([obs["polygon_mask"], obs["circle_mask"]])
        ji = obs["joint_indexes"]
        joints = _mlp(self, jnp.concatenate([obs["joints"], bodies[ji[:, 0]], bodies[ji[:, 1]]], axis=-1), (w, w),
                      act, "joints")
        thrusters = _mlp(self, jnp.concatenate([obs["thrusters"], bodies[obs["thruster_indexes"]]], axis=-1),
                         (w, w), act, "thrusters")
        tokens = jnp.concatenate([bodies, joints, thrusters], axis=0)
        mask = jnp.concatenate([body_mask, obs["joint_mask"], obs["thruster_mask"]])
        # every token may attend to every active token; inactive query rows attend to all so softmax stays finite
        attend = mask[None, :] | ~mask[:, None]
        mixed = nn.MultiHeadDotProductAttention(num_heads=self.heads, qkv_features=w)(
            nn.LayerNorm()(tokens), mask=attend[None])
        tokens = tokens + mixed
        tokens = tokens + _mlp(self, nn.LayerNorm()(tokens), (w, w), act, "mix", final_activation=False)
        pooled = _masked_pool(tokens, mask)
        # the two-pass variance: with flax's default E[x^2] - E[x]^2 the norm's backward cancelled rounding up to
        # 0.25 % relative differences in Adam's moments between 2 processes and 1 (test_multihost's default run)
        return nn.LayerNorm(use_fast_variance=False)(pooled) if self.pooled_norm else pooled


class ActorCritic(nn.Module):
    """obs (batched: a leading axis) -> (logits or means, value)."""

    network: str = "entity"
    action: str = "multi_discrete"
    width: int = 64
    hidden: int = 128
    activation: str = "tanh"
    pooled_norm: bool = True  # entity network only: a LayerNorm on the pooled summary (see the module docstring)

    @nn.compact
    def __call__(self, obs) -> tuple[jax.Array, jax.Array]:
        act = check_activation(self.activation)
        if self.network == "entity":
            # intermediates (only collected when asked for) get the batch axis like the observations
            features = nn.vmap(EntityEncoder, variable_axes={"params": None, "intermediates": 0},
                               split_rngs={"params": False})(width=self.width, activation=act,
                                                                pooled_norm=self.pooled_norm)(obs)
        elif self.network == "flat":
            features = _mlp(self, obs, (self.hidden, self.hidden), act, "flat")
        elif self.network == "pixels":
            x = obs
            for i, (channels, stride) in enumerate(((16, 2), (32, 2), (32, 2))):
                x = _hidden(self, nn.Conv(channels, (3, 3), strides=(stride, stride))(x), act, f"conv_{i}")
            features = _mlp(self, x.reshape(x.shape[0], -1), (self.hidden,), act, "pixels")
        else:
            raise ValueError(f"unknown network {self.network!r}: use one of {', '.join(NETWORK_TYPES)}")
        outputs, value = Heads(policy_outputs(self.action), self.hidden, act)(features)
        if self.action == "continuous":  # a state-independent log std, appended to the means
            log_std = self.param("log_std", nn.initializers.constant(-0.5), (outputs.shape[-1],))
            outputs = jnp.concatenate([outputs, jnp.broadcast_to(log_std, outputs.shape)], axis=-1)
        return outputs, value
