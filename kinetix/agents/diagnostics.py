"""What the per-episode diagnostics of a trained agent share (kinetix.agents.binding_entropy,
kinetix.agents.health): loading a multi_discrete agent, one episode per level with sampled actions (as
`kinetix eval`), and the command line AGENT [--level levels ...] [--steps 64] [--seed 0] [--json]."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import jax2d
from kinetix.actions import action_space
from kinetix.agents import checkpoint, distributions
from kinetix.agents.checkpoint import Checkpoint, CheckpointError
from kinetix.agents.evaluate import LevelBatch, level_batches
from kinetix.agents.policy import load_network, resolve
from kinetix.agents.rollout import fresh_state, keep_finished
from kinetix.bindings import bound_bindings
from kinetix.cli import positive_int
from kinetix.level import LevelError, LevelFile
from kinetix.level_source import eval_levels

ACTION = "multi_discrete"
CHOICES = tuple(int(n) for n in action_space(ACTION).nvec)  # (3, 3, 3, 3, 2, 2)

Measure = Callable[..., dict]  # measure(agent, levels, steps=..., seed=...) -> a JSON-able result
# observe(obs, live, acc) -> (head outputs, acc): one agent step's measurement, accumulated into acc under jit
Observe = Callable[[Any, jax.Array, Any], tuple[jax.Array, Any]]
# init(obs, live) -> acc: the zero accumulator for a batch's first observation
Init = Callable[[Any, jax.Array], Any]
# per compile group: (network, params) -> (init, observe)
Probe = Callable[[Any, Any], tuple[Init, Observe]]


def load_multi_discrete(agent: str) -> tuple[Path, Checkpoint]:
    """(checkpoint directory, checkpoint) of `agent` (a directory or general), refused with a CheckpointError when
    it names no network or acts in another space than multi_discrete, where the per-binding measures are defined."""
    where = resolve(agent)
    if isinstance(where, str):
        raise CheckpointError(f"{agent!r} has no network to measure: give a checkpoint directory or general")
    ckpt = checkpoint.load(where)
    if ckpt.env["action"] != ACTION:
        raise CheckpointError(f"agent {agent} acts in the {ckpt.env['action']!r} space; this measure is defined "
                              f"for {ACTION} agents")
    return where, ckpt


def episodes(agent: str, where: Path, ckpt: Checkpoint, levels: list[tuple[str, LevelFile]], steps: int,
             seed: int, probe: Probe) -> Iterator[tuple[Any, np.ndarray]]:
    """One episode per level with sampled actions, its first `steps` agent steps, compile group by compile group.
    Yields (acc, bound) per group: the accumulator `probe`'s observe built over the steps (it sees `live`, false
    once a level's episode has ended, and masks those steps itself), and each level's bound bindings (B, 6)."""
    key = jax.random.key(seed)
    for batch in level_batches(levels, ckpt.env["observation"]):
        init, observe = probe(*load_network(where, batch.env, agent))
        key, sub = jax.random.split(key)
        acc, bound = _scan(batch, init, observe, sub, min(steps, batch.steps))
        yield jax.tree.map(np.asarray, acc), np.asarray(bound)


def _scan(batch: LevelBatch, init: Init, observe: Observe, key: jax.Array, steps: int) -> tuple[Any, jax.Array]:
    step = jax.vmap(batch.env.step_no_reset, in_axes=(None, 0, 0, 0))

    def one(carry, step_key):
        state, obs, done, acc = carry
        outputs, acc = observe(obs, ~done, acc)
        action_key, env_key = jax.random.split(step_key)
        action = distributions.sample(action_key, outputs, ACTION)
        obs, next_state, _, terminated, truncated, _ = step(env_key, state, action, batch.params)
        state = keep_finished(done, state, next_state)
        return (state, obs, done | terminated | truncated, acc), None

    @jax2d.jit
    def run(levels, key):
        state = jax.vmap(fresh_state)(levels)
        obs = jax.vmap(batch.env.observe)(state)
        done = jnp.zeros((len(batch.members),), bool)
        (_, _, _, acc), _ = jax.lax.scan(one, (state, obs, done, init(obs, ~done)), jax.random.split(key, steps))
        return acc, jax.vmap(bound_bindings)(levels)

    return run(batch.levels, key)


def run(name: str, doc: str, measure: Measure, argv: list[str] | None
        ) -> int | tuple[argparse.Namespace, list[tuple[str, LevelFile]], dict]:
    """Parse `argv`, load the levels and measure. Returns an exit status when done (2 with a one-line error on
    stderr for a bad agent or level; 0 after printing --json), else (args, levels, result) for the caller's table."""
    parser = argparse.ArgumentParser(prog=f"python -m kinetix.agents.{name}", description=doc.split("\n\n")[0])
    parser.add_argument("agent", help="a checkpoint directory, or general")
    parser.add_argument("--level", nargs="+", default=["levels"],
                        help="level files, directories or generated sets (as kinetix eval; default levels)")
    parser.add_argument("--steps", type=positive_int, default=64, help="agent steps per episode measured (64)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")
    args = parser.parse_args(argv)
    try:
        levels = [named for spec in args.level for named in eval_levels(spec)]
        result = measure(args.agent, levels, steps=args.steps, seed=args.seed)
    except (LevelError, CheckpointError) as error:
        print(f"{name}: {error}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(result))
        return 0
    return args, levels, result
