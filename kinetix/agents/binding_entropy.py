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

import jax.numpy as jnp
import numpy as np

from kinetix.agents import diagnostics, distributions
from kinetix.agents.diagnostics import CHOICES
from kinetix.level import LevelFile

NAMES = ("motor 0", "motor 1", "motor 2", "motor 3", "thruster 0", "thruster 1")


def _probe(network, params):
    """Per level: (entropy summed over its live steps (6,), live steps counted)."""
    def init(obs, live):
        return jnp.zeros(live.shape + (len(CHOICES),)), jnp.zeros(live.shape, jnp.int32)

    def observe(obs, live, acc):
        total, count = acc
        outputs, _ = network.apply({"params": params}, obs)
        total = total + jnp.where(live[:, None], distributions.binding_entropies(outputs), 0.0)
        return outputs, (total, count + live)

    return init, observe


def binding_entropy(agent: str, levels: list[tuple[str, LevelFile]], steps: int = 64, seed: int = 0) -> dict:
    """Per binding: mean entropy on the levels that use it ("used") and on those that do not ("unused"), the
    number of levels of each, the uniform maximum, and the used bindings' mean entropy as a fraction of it."""
    where, ckpt = diagnostics.load_multi_discrete(agent)
    sums = {"used": np.zeros(len(CHOICES)), "unused": np.zeros(len(CHOICES))}
    counts = {"used": np.zeros(len(CHOICES)), "unused": np.zeros(len(CHOICES))}
    n_levels = {"used": np.zeros(len(CHOICES), int), "unused": np.zeros(len(CHOICES), int)}
    for (total, count), bound in diagnostics.episodes(agent, where, ckpt, levels, steps, seed, _probe):
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
