"""Is a trained network still alive? Its dead units, layer by layer, and how much its policy depends on the state.

    python -m kinetix.agents.health AGENT [--level levels ...] [--steps 64] [--seed 0] [--json]

Why: a relu unit whose pre-activation is negative on every input passes no gradient and never recovers. The first
general run (kinetix/agents/general/sfl-large) lost its actor that way: by 109M env steps all 128 units of the
actor's second hidden layer were dead on every state, so its logits were one constant vector, the same
distribution on every level, and training could not change that any more. Its summed entropy rose toward uniform,
which looked like an entropy bonus set too strong; this module measures the cause.

Measured over the states of one episode per level with sampled actions (as `kinetix eval`), the first `steps`
agent steps, counting only steps before the episode ends:
  - per hidden layer (kinetix.agents.networks sows each one's pre-activation): a unit is *dead* when the
    activation's slope is below DEAD_SLOPE at every measured input (no gradient reaches its weights); *active* is
    the share of (input, unit) pairs above it. Entity layers count only the rows of real entities, not padding.
  - per binding, on the levels that use it (kinetix.bindings.bound_bindings): the information the policy's choice
    carries about the state, I(S; A) = H(mean policy) - mean H(policy), in nats. 0 means one fixed distribution
    whatever the state: a policy that cannot act on what it sees. Only for multi_discrete agents.
"""

from __future__ import annotations

import sys

import jax
import jax.numpy as jnp
import numpy as np

from kinetix.agents import diagnostics, distributions
from kinetix.agents.diagnostics import CHOICES
from kinetix.agents.networks import DEAD_SLOPE, pre_activations, slope
from kinetix.level import LevelFile

# entity layers (networks.EntityEncoder labels) and the observation masks of their rows
ENTITY_ROWS = {"polygons": ("polygon_mask",), "circles": ("circle_mask",), "joints": ("joint_mask",),
               "thrusters": ("thruster_mask",),
               "mix": ("polygon_mask", "circle_mask", "joint_mask", "thruster_mask")}


def _rows(label: str, pre: jax.Array, obs, live: jax.Array) -> jax.Array:
    """Which rows of `pre` (all axes but the last) are real inputs: live states, and real entities."""
    kind = label.rsplit("_", 1)[0]
    if kind in ENTITY_ROWS:
        entities = jnp.concatenate([obs[name] for name in ENTITY_ROWS[kind]], axis=-1)
        return entities & live[:, None]
    return jnp.broadcast_to(live.reshape(live.shape + (1,) * (pre.ndim - 2)), pre.shape[:-1])


def _probe(activation: str):
    """Per hidden layer: (any live input alive (units,), alive (input, unit) pairs (units,), real inputs); per level:
    policy probabilities and entropies summed over its live steps, and its live steps counted."""
    def probe(network, params):
        def layer_stats(obs, live):
            (outputs, _), state = network.apply({"params": params}, obs, mutable=["intermediates"])
            stats = {}
            for label, pre in pre_activations(state["intermediates"]).items():
                rows = _rows(label, pre, obs, live)
                alive = (slope(activation, pre) >= DEAD_SLOPE) & rows[..., None]
                axes = tuple(range(pre.ndim - 1))
                stats[label] = (alive.any(axes), alive.sum(axes).astype(jnp.float32), rows.sum().astype(jnp.float32))
            return outputs, stats

        def init(obs, live):
            _, zero_stats = jax.eval_shape(layer_stats, obs, live)
            b = live.shape[0]
            return {"layers": jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), zero_stats),
                    "probs": [jnp.zeros((b, n)) for n in CHOICES], "entropy": jnp.zeros((b, len(CHOICES))),
                    "count": jnp.zeros((b,), jnp.int32)}

        def observe(obs, live, acc):
            outputs, stats = layer_stats(obs, live)
            probs = [jax.nn.softmax(p) for p in jnp.split(outputs, np.cumsum(CHOICES)[:-1].tolist(), axis=-1)]
            entropies = distributions.binding_entropies(outputs)
            return outputs, {
                "layers": jax.tree.map(lambda a, b: a | b if a.dtype == bool else a + b, acc["layers"], stats),
                "probs": [a + jnp.where(live[:, None], p, 0.0) for a, p in zip(acc["probs"], probs, strict=True)],
                "entropy": acc["entropy"] + jnp.where(live[:, None], entropies, 0.0),
                "count": acc["count"] + live}

        return init, observe

    return probe


def health(agent: str, levels: list[tuple[str, LevelFile]], steps: int = 64, seed: int = 0) -> dict:
    """{"layers": {label: {"units", "dead", "active"}}, "information": per binding I(S; A) in nats on the levels
    that use it (None where none does), "information_mean", "activation", "states"}."""
    where, ckpt = diagnostics.load_multi_discrete(agent)
    activation = ckpt.train_config.activation
    alive: dict[str, np.ndarray] = {}
    active: dict[str, float] = {}
    rows: dict[str, float] = {}
    probs = [np.zeros(n) for n in CHOICES]  # summed over used states, per binding
    entropy, used = np.zeros(len(CHOICES)), np.zeros(len(CHOICES))
    states = 0
    for acc, bound in diagnostics.episodes(agent, where, ckpt, levels, steps, seed, _probe(activation)):
        for label, (any_alive, active_sum, row_count) in acc["layers"].items():
            alive[label] = alive.get(label, np.zeros_like(any_alive)) | any_alive
            active[label] = active.get(label, 0.0) + float(active_sum.sum())
            rows[label] = rows.get(label, 0.0) + float(row_count)
        weights = acc["count"][:, None] * bound  # (B, 6): states counted on a binding's using levels
        for i in range(len(CHOICES)):
            probs[i] += (acc["probs"][i] * bound[:, i:i + 1]).sum(0)
        entropy += (acc["entropy"] * bound).sum(0)
        used += weights.sum(0)
        states += int(acc["count"].sum())
    information = []
    for i in range(len(CHOICES)):
        if not used[i]:
            information.append(None)
            continue
        mean = probs[i] / used[i]
        mean_entropy = -float(np.sum(mean * np.log(np.maximum(mean, 1e-30))))
        information.append(max(0.0, mean_entropy - float(entropy[i] / used[i])))
    layers = {label: {"units": int(alive[label].size), "dead": float(1.0 - alive[label].mean()),
                      "active": active[label] / (rows[label] * alive[label].size) if rows[label] else None}
              for label in sorted(alive)}
    known = [x for x in information if x is not None]
    return {"activation": activation, "states": states, "layers": layers, "information": information,
            "information_mean": float(np.mean(known)) if known else None}


def main(argv: list[str] | None = None) -> int:
    outcome = diagnostics.run("health", __doc__, health, argv)
    if isinstance(outcome, int):
        return outcome
    args, levels, result = outcome
    print(f"{'layer':<12} {'units':>5} {'dead':>6} {'active':>6}   ({result['activation']}, {len(levels)} levels, "
          f"{result['states']} states, agent {args.agent})")
    for label, layer in result["layers"].items():
        active = "     -" if layer["active"] is None else f"{layer['active']:6.1%}"
        print(f"{label:<12} {layer['units']:>5} {layer['dead']:6.1%} {active}")
    info = " ".join("-" if x is None else f"{x:.3f}" for x in result["information"])
    print(f"policy information I(state; action) per binding, nats, on the levels using it: {info}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
