"""How decided a policy is, binding by binding: its entropy along its own episodes, split into the bindings a level
uses and the ones it does not.

    python -m kinetix.agents.binding_entropy AGENT [--level levels ...] [--steps 64] [--seed 0] [--json]

Why: training reports one entropy, the sum over the six categoricals of the multi_discrete space (4 motor bindings
of 3 choices, 2 thruster bindings of 2; at most 4 ln 3 + 2 ln 2 = 5.78). A binding no driven joint or thruster
listens to (kinetix.bindings.bound_bindings) changes nothing in the level, so only the entropy bonus acts on it and
it drifts to uniform; the sum cannot say whether the policy has committed on the bindings that matter. This
splits it: for each binding, the mean entropy over the steps of the levels that use it, and over those that do not.

Protocol: one episode per level with sampled actions (as `kinetix eval`), the first `steps` agent steps, counting
only steps before the episode ends. Only for multi_discrete agents.
"""

from __future__ import annotations

import sys

import jax
import jax.numpy as jnp
import numpy as np

import jax2d
from kinetix.actions import action_space
from kinetix.agents import checkpoint, diagnostics, distributions
from kinetix.agents.checkpoint import CheckpointError
from kinetix.agents.evaluate import LevelBatch, level_batches
from kinetix.agents.policy import load_network, resolve
from kinetix.agents.rollout import fresh_state, keep_finished
from kinetix.bindings import bound_bindings
from kinetix.level import LevelFile

ACTION = "multi_discrete"
CHOICES = tuple(int(n) for n in action_space(ACTION).nvec)  # (3, 3, 3, 3, 2, 2)
NAMES = ("motor 0", "motor 1", "motor 2", "motor 3", "thruster 0", "thruster 1")


def _batch_entropy(batch: LevelBatch, network, params, key: jax.Array, steps: int) -> tuple[np.ndarray, ...]:
    """(entropy sums (B, 6), steps counted (B,), bound (B, 6)) for one compile group, one episode per level."""
    env = batch.env
    step = jax.vmap(env.step_no_reset, in_axes=(None, 0, 0, 0))

    def one(carry, step_key):
        state, obs, done, total, count = carry
        outputs, _ = network.apply({"params": params}, obs)
        live = ~done
        total = total + jnp.where(live[:, None], distributions.binding_entropies(outputs), 0.0)
        action_key, env_key = jax.random.split(step_key)
        action = distributions.sample(action_key, outputs, ACTION)
        obs, next_state, _, terminated, truncated, _ = step(env_key, state, action, batch.params)
        state = keep_finished(done, state, next_state)
        return (state, obs, done | terminated | truncated, total, count + live), None

    @jax2d.jit
    def run(levels, key):
        state = jax.vmap(fresh_state)(levels)
        obs = jax.vmap(env.observe)(state)
        b = len(batch.members)
        init = (state, obs, jnp.zeros((b,), bool), jnp.zeros((b, len(CHOICES))), jnp.zeros((b,), jnp.int32))
        (_, _, _, total, count), _ = jax.lax.scan(one, init, jax.random.split(key, min(steps, batch.steps)))
        return total, count, jax.vmap(bound_bindings)(levels)

    return tuple(np.asarray(x) for x in run(batch.levels, key))


def binding_entropy(agent: str, levels: list[tuple[str, LevelFile]], steps: int = 64, seed: int = 0) -> dict:
    """Per binding: mean entropy on the levels that use it ("used") and on those that do not ("unused"), the
    number of levels of each, the uniform maximum, and the used bindings' mean entropy as a fraction of it."""
    where = resolve(agent)
    if isinstance(where, str):
        raise CheckpointError(f"{agent!r} has no network to measure: give a checkpoint directory or general")
    trained = checkpoint.load(where).env
    if trained["action"] != ACTION:
        raise CheckpointError(f"agent {agent} acts in the {trained['action']!r} space; binding entropy is defined "
                              f"for {ACTION} agents")
    sums = {"used": np.zeros(len(CHOICES)), "unused": np.zeros(len(CHOICES))}
    counts = {"used": np.zeros(len(CHOICES)), "unused": np.zeros(len(CHOICES))}
    n_levels = {"used": np.zeros(len(CHOICES), int), "unused": np.zeros(len(CHOICES), int)}
    key = jax.random.key(seed)
    for batch in level_batches(levels, trained["observation"]):
        network, params = load_network(where, batch.env, agent)
        key, sub = jax.random.split(key)
        total, count, bound = _batch_entropy(batch, network, params, sub, steps)
        for name, mask in (("used", bound), ("unused", ~bound)):
            sums[name] += (total * mask).sum(0)
            counts[name] += (count[:, None] * mask).sum(0)
            n_levels[name] += mask.sum(0)
    maximum = np.log(np.asarray(CHOICES, float))
    mean = {name: [float(s / c) if c else None for s, c in zip(sums[name], counts[name], strict=True)]
            for name in sums}
    used = [m / x for m, x in zip(mean["used"], maximum, strict=True) if m is not None]
    return {"bindings": list(NAMES), "used": mean["used"], "unused": mean["unused"],
            "levels_using": n_levels["used"].tolist(), "levels_not_using": n_levels["unused"].tolist(),
            "maximum": maximum.tolist(), "used_fraction_of_maximum": float(np.mean(used)) if used else None}


def main(argv: list[str] | None = None) -> int:
    outcome = diagnostics.run("binding_entropy", __doc__, binding_entropy, argv)
    if isinstance(outcome, int):
        return outcome
    args, levels, result = outcome
    fmt = lambda v: "    -" if v is None else f"{v:5.3f}"
    print(f"{'binding':<11} {'used':>5} ({'levels':>6})  {'unused':>6} ({'levels':>6})  maximum   "
          f"({len(levels)} levels, {args.steps} steps, agent {args.agent})")
    for i, name in enumerate(result["bindings"]):
        print(f"{name:<11} {fmt(result['used'][i])} ({result['levels_using'][i]:>6})  "
              f"{fmt(result['unused'][i]):>6} ({result['levels_not_using'][i]:>6})  {result['maximum'][i]:.3f}")
    fraction = result["used_fraction_of_maximum"]
    print("no level uses any binding" if fraction is None else
          f"used bindings' entropy: {fraction:.0%} of the uniform policy's")
    return 0


if __name__ == "__main__":
    sys.exit(main())
