"""`kinetix eval`: the solve rate of an agent over `attempts` episodes per level.

Levels are grouped by size class and frame skip (both compile-time), so each group compiles once; within a
group every level keeps its own episode length, shaping and actuator scales (EnvParams are batched).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

import jax
import jax.numpy as jnp
import numpy as np

import jax2d
from kinetix.agents.checkpoint import CheckpointError
from kinetix.agents.policy import load_policy, required_observation
from kinetix.agents.rollout import run_episodes
from kinetix.env import EnvConfig, EnvParams, KinetixEnv, make_env
from kinetix.level import Level, LevelError, LevelFile
from kinetix.level_source import eval_levels
from kinetix.reset_fns import stack_levels

ATTEMPTS = 20


@dataclasses.dataclass(frozen=True)
class LevelBatch:
    """Levels that share one compile: one size class and frame skip, stacked along a leading axis."""

    env: KinetixEnv
    members: list[int]  # their indices in the list given to level_batches
    levels: Level  # stacked
    params: EnvParams  # stacked: every level keeps its own episode length, shaping and actuator scales
    steps: int  # the longest episode among them (agent steps)


def level_batches(levels: list[tuple[str, LevelFile]], observation: str) -> list[LevelBatch]:
    """`levels` ((name, LevelFile) pairs) grouped by size class and frame skip (both compile-time)."""
    groups: dict[tuple[str, int], list[int]] = {}
    for i, (_, lf) in enumerate(levels):
        groups.setdefault((lf.size.name, lf.params.frame_skip), []).append(i)
    batches = []
    for (size, frame_skip), members in groups.items():
        files = [levels[i][1] for i in members]
        env = make_env(EnvConfig(size, observation=observation, frame_skip=frame_skip), files[0])
        params = jax.tree.map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]),
                              *[EnvParams.from_level_params(lf.params) for lf in files])
        batches.append(LevelBatch(env, members, stack_levels(files), params,
                                  max(lf.params.max_timesteps for lf in files)))
    return batches


def evaluate(agent: str, levels: list[tuple[str, LevelFile]], attempts: int = ATTEMPTS, seed: int = 0,
             deterministic: bool = False) -> list[dict]:
    """[{"level", "solve_rate", "mean_return"}] in the order of `levels` ((name, LevelFile) pairs)."""
    observation = required_observation(agent) or "entity"
    results: list[dict | None] = [None] * len(levels)
    key = jax.random.key(seed)
    for batch in level_batches(levels, observation):
        env, members = batch.env, batch.members
        policy = load_policy(agent, env, deterministic=deterministic)
        repeat = lambda x: jnp.repeat(x, attempts, axis=0)
        act = lambda k, obs: policy.act(k, obs)[0]
        key, sub = jax.random.split(key)
        run = jax2d.jit(lambda lv, p, k: run_episodes(env, p, act, lv, k, batch.steps))
        solved, total = run(jax.tree.map(repeat, batch.levels), jax.tree.map(repeat, batch.params), sub)
        solved = np.asarray(solved).reshape(len(members), attempts)
        total = np.asarray(total).reshape(len(members), attempts)
        for j, i in enumerate(members):
            results[i] = {"level": levels[i][0], "solve_rate": float(solved[j].mean()),
                          "mean_return": float(total[j].mean())}
    return results


def run(args: argparse.Namespace) -> int:
    try:
        levels = [named for spec in args.level for named in eval_levels(spec)]
        results = evaluate(args.agent, levels, attempts=args.attempts, seed=args.seed,
                           deterministic=args.deterministic)
    except (LevelError, CheckpointError) as error:
        print(f"kinetix eval: {error}", file=sys.stderr)
        return 2
    if args.json:
        for r in results:
            print(json.dumps(r))
        return 0
    width = max(len(r["level"]) for r in results)
    print(f"{'level':<{width}}  solve rate  mean return   ({args.attempts} attempts per level, agent {args.agent})")
    for r in results:
        print(f"{r['level']:<{width}}  {r['solve_rate']:10.2f}  {r['mean_return']:11.3f}")
    solved = sum(r["solve_rate"] >= 0.9 for r in results)
    print(f"mean solve rate {np.mean([r['solve_rate'] for r in results]):.3f}; "
          f"{solved}/{len(results)} levels solved at >= 90%")
    return 0
