"""`kinetix bench train`: PPO training throughput (env steps per second, updates included) per size class.

Trains on random levels of each size (dr) and times the jitted chunks after the first one, so compiling
is reported separately. Prints numbers only; nothing here passes or fails.
"""

from __future__ import annotations

import argparse
import json
import time

import jax

import jax2d
from kinetix.agents import curricula
from kinetix.agents.ppo import TrainConfig, make_train
from kinetix.env import EnvConfig, EnvParams, make_env
from kinetix.level import WALLS_SOLVER, size_class
from kinetix.level_source import RANDOM_DENSE_REWARD


def measure(size: str, num_envs: int, num_steps: int, chunks: int, updates_per_call: int) -> dict:
    from kinetix.generate import sample_level

    sc = size_class(size)
    generator = lambda key: sample_level(key, sc)
    env = make_env(EnvConfig(sc, solver=WALLS_SOLVER), generator)  # as `kinetix train` on random levels
    config = TrainConfig(num_envs=num_envs, num_steps=num_steps, updates_per_call=updates_per_call,
                         total_timesteps=num_envs * num_steps * updates_per_call * (chunks + 1))
    trainer = make_train(config, env, EnvParams(dense_reward_scale=RANDOM_DENSE_REWARD),
                         curricula.domain_randomisation(generator))
    start = time.perf_counter()
    runner = jax2d.jit(trainer.init)(jax.random.key(0))
    runner, metrics = trainer.run(runner)
    jax.block_until_ready(metrics)
    first = time.perf_counter() - start
    start = time.perf_counter()
    for _ in range(chunks):
        runner, metrics = trainer.run(runner)
    jax.block_until_ready(metrics)
    elapsed = time.perf_counter() - start
    steps = chunks * updates_per_call * config.batch_size
    return {"size": size, "num_envs": num_envs, "num_steps": num_steps, "env_steps": steps,
            "seconds": round(elapsed, 2), "steps_per_second": round(steps / elapsed, 1),
            "first_chunk_seconds": round(first, 2), "devices": jax.local_device_count()}


def run(args: argparse.Namespace) -> int:
    for size in args.sizes:
        result = measure(size, args.num_envs, args.num_steps, args.chunks, args.updates_per_call)
        if args.json:
            print(json.dumps(result), flush=True)
        else:
            print(f"size {size}: {result['steps_per_second']:9.1f} env steps/s with updates "
                  f"({result['num_envs']} envs, {result['env_steps']} steps in {result['seconds']} s; "
                  f"first chunk incl. compile "
                  f"{result['first_chunk_seconds']} s)", flush=True)
    return 0
