"""`kinetix bench train`: PPO training throughput (env steps per second, updates included) per size class.

Trains on random levels of each size (dr; `all`: random-all in size groups as `kinetix train` runs it,
`all-padded`: every level padded to l, as runs before size groups), the env batch split over the CPU devices
(`--devices`, default one per core, as `kinetix bench env` does), and times the jitted chunks after the first one,
so compiling is reported separately. Prints numbers only; nothing here passes or fails.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax

import jax2d
from kinetix.agents import curricula
from kinetix.agents.ppo import TrainConfig, make_train
from kinetix.agents.sharding import batch_sharder, local_mesh
from kinetix.devices import batch_devices
from kinetix.env import EnvConfig, EnvParams, make_env
from kinetix.level import WALLS_SOLVER, size_class
from kinetix.level_source import RANDOM_DENSE_REWARD


def measure(size: str, num_envs: int, num_steps: int, chunks: int, updates_per_call: int, timed: bool = True,
            **ppo: int) -> dict:
    """PPO env steps per second with updates: the first chunk (compiling) apart, then `chunks` timed ones.
    timed=False stops after the first chunk (it only compiles, e.g. into the persistent cache). `ppo`: other
    TrainConfig fields (update_epochs, num_minibatches), TrainConfig's defaults where not given."""
    from kinetix.agents.train import random_all_groups, size_groups_for
    from kinetix.generate import sample_level
    from kinetix.level_source import level_source

    config = TrainConfig(num_envs=num_envs, num_steps=num_steps, updates_per_call=updates_per_call,
                         total_timesteps=num_envs * num_steps * updates_per_call * (chunks + 1), **ppo)
    devices = batch_devices(num_envs)  # as `kinetix train` and `kinetix bench env`: the env batch over every device
    sharder = lambda n: batch_sharder(local_mesh(), n) if devices > 1 else None
    groups = None
    if size in ("all", "all-padded"):  # random-all as `kinetix train` steps it: in size groups, or padded to l
        source = level_source("random-all")
        generator = source.generator
        env = make_env(source.env_config("entity", "multi_discrete"), generator)
        if size == "all":
            groups = random_all_groups(size_groups_for(config, devices), None, "entity", "multi_discrete",
                                       curricula.CurriculumConfig(), None, lambda env: None, sharder)
    else:
        sc = size_class(size)
        generator = lambda key: sample_level(key, sc)
        env = make_env(EnvConfig(sc, solver=WALLS_SOLVER), generator)  # as `kinetix train` on random levels
    trainer = make_train(config, env, EnvParams(dense_reward_scale=RANDOM_DENSE_REWARD),
                         curricula.domain_randomisation(generator), shard=sharder(num_envs), groups=groups)
    start = time.perf_counter()
    runner = jax2d.jit(trainer.init)(jax.random.key(0))
    runner, metrics = trainer.run(runner)
    jax.block_until_ready(metrics)
    first = time.perf_counter() - start
    if not timed:
        return {"size": size, "num_envs": num_envs, "first_chunk_seconds": round(first, 2)}
    start = time.perf_counter()
    for _ in range(chunks):
        runner, metrics = trainer.run(runner)
    jax.block_until_ready(metrics)
    elapsed = time.perf_counter() - start
    steps = chunks * updates_per_call * config.batch_size
    return {"size": size, "num_envs": num_envs, "num_steps": num_steps, "update_epochs": config.update_epochs,
            "num_minibatches": config.num_minibatches, "env_steps": steps,
            "seconds": round(elapsed, 2), "steps_per_second": round(steps / elapsed, 1),
            "first_chunk_seconds": round(first, 2), "devices": devices}


def env_speed(size: str, num_envs: int) -> dict:
    """`kinetix bench env`'s rollout of the same size class at the same batch (its reference level), for the ratio."""
    from kinetix.bench.env import default_level_paths, measure_rollout
    from kinetix.levels import load_level

    path = default_level_paths([size])[0]
    return measure_rollout(load_level(path), path.stem, num_envs, 100, cold=False)


def run(args: argparse.Namespace) -> int:
    ppo = {name: value for name in ("update_epochs", "num_minibatches") if (value := getattr(args, name)) is not None}
    try:  # the settings' own checks (e.g. minibatches that do not divide the batch) before anything compiles
        TrainConfig(num_envs=args.num_envs, num_steps=args.num_steps, **ppo)
    except ValueError as error:
        print(f"kinetix bench train: {error}", file=sys.stderr)
        return 2
    for size in args.sizes:
        result = measure(size, args.num_envs, args.num_steps, args.chunks, args.updates_per_call, **ppo)
        if args.env and size.startswith("all"):
            print(f"size {size}: no reference level to compare with (--env measures s, m and l)", flush=True)
        elif args.env:
            env = env_speed(size, args.num_envs)
            result.update(env_level=env["level"], env_steps_per_second=round(env["steps_per_s"], 1),
                          share_of_env=round(result["steps_per_second"] / env["steps_per_s"], 3))
        if args.json:
            print(json.dumps(result), flush=True)
            continue
        line = (f"size {size}: {result['steps_per_second']:9.1f} env steps/s with updates ({result['num_envs']} envs "
                f"on {result['devices']} device(s), {result['update_epochs']} epochs of {result['num_minibatches']} "
                f"minibatches, {result['env_steps']} steps in {result['seconds']} s; first chunk "
                f"incl. compile {result['first_chunk_seconds']} s)")
        if "share_of_env" in result:
            line += (f"; env alone {result['env_steps_per_second']:.0f} steps/s ({result['env_level']}): training "
                     f"keeps {100 * result['share_of_env']:.1f}%")
        print(line, flush=True)
    return 0
