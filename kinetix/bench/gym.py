"""`kinetix bench gym`: the Gymnasium vector env (kinetix.gym) against the JAX env at the same batch, side by side.

For each level and batch size, in one process on the same devices:
- jax env: `kinetix bench env`'s rollout (kinetix.bench.env.compile_rollout): `steps` auto-resetting env steps with
  random multi-discrete actions in one jitted scan, no Python between steps (XLA drops the unused observation);
- gym vector env: KinetixVectorEnv.step called `steps` times from Python with NumPy random actions, each call
  returning NumPy observations, rewards, flags and infos (the observation type of --observation; entity by
  default); the actions are drawn beforehand.
Both are built first, then timed in turn (REPEATS rounds, medians reported), so a shared machine's load falls on
both alike. The ratio is gym / jax (the issue's bar: at least 0.5 at 512 environments). Needs the gym extra.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from kinetix.bench.engine import SEED, machine_row, machine_summary, measured_on
from kinetix.bench.env import compile_rollout, load_bench_levels

ACTION_POOL = 16  # distinct action batches cycled through (drawing them is not what is measured)
WARMUP_STEPS = 5
REPEATS = 3  # interleaved jax / gym measurements; the median of each is reported (the machine may be shared)


class GymRun:
    """KinetixVectorEnv(path, num_envs=batch) stepped `steps` times from Python per call, NumPy actions drawn
    beforehand."""

    def __init__(self, path: Path, batch: int, steps: int, observation: str):
        import numpy as np

        from kinetix.gym import KinetixVectorEnv

        self.envs = KinetixVectorEnv(str(path), num_envs=batch, observation=observation)
        self.steps = steps
        start = time.perf_counter()
        self.envs.reset(seed=SEED)  # compiles the one program (or loads it from the persistent cache)
        self.compile_s = time.perf_counter() - start
        rng = np.random.default_rng(SEED)
        nvec = self.envs.single_action_space.nvec
        self.pool = [rng.integers(0, nvec, size=(batch, len(nvec))).astype(np.int32) for _ in range(ACTION_POOL)]
        for i in range(WARMUP_STEPS):
            self.envs.step(self.pool[i % ACTION_POOL])
        self.episodes_ended = 0

    def __call__(self) -> float:
        """Seconds for `steps` steps."""
        start = time.perf_counter()
        for i in range(self.steps):
            _, _, terminated, truncated, _ = self.envs.step(self.pool[i % ACTION_POOL])
            self.episodes_ended += int(terminated.sum() + truncated.sum())
        return time.perf_counter() - start


def _timed(run) -> float:
    import jax

    start = time.perf_counter()
    jax.block_until_ready(run())
    return time.perf_counter() - start


def compare(path: Path, batch: int, steps: int, observation: str = "entity", repeats: int = REPEATS) -> list[dict]:
    """[jax env result, gym result, ratio] for one level and batch: both built first, then measured in turn
    `repeats` times (one run each per round), so load on a shared machine falls on both alike."""
    from kinetix.devices import batch_devices
    from kinetix.levels import load_level

    level_file = load_level(path)
    size, name = level_file.size.name, path.stem
    jax_run, jax_compile_s, _ = compile_rollout(level_file, batch, steps, cold=False)
    _timed(jax_run)  # warm-up
    gym_run = GymRun(path, batch, steps, observation)
    jax_times, gym_times = [], []
    for _ in range(repeats):
        jax_times.append(_timed(jax_run))
        gym_times.append(gym_run())
    gym_run.envs.close()
    jax_s, gym_s = sorted(jax_times)[repeats // 2], sorted(gym_times)[repeats // 2]
    common = {"size": size, "level": name, "batch": batch, "steps": steps, "repeats": repeats,
              "devices": batch_devices(batch), **measured_on()}
    jax_env = {"what": "env", **common, "steps_per_s": batch * steps / jax_s, "seconds": jax_s,
               "compile_s": jax_compile_s}
    gym_env = {"what": "gym", **common, "observation": observation, "steps_per_s": batch * steps / gym_s,
               "seconds": gym_s, "compile_s": gym_run.compile_s, "episodes_ended": gym_run.episodes_ended}
    ratio = {"what": "gym_vs_jax", "size": size, "level": name, "batch": batch,
             "jax_steps_per_s": jax_env["steps_per_s"], "gym_steps_per_s": gym_env["steps_per_s"],
             "ratio": jax_s / gym_s}
    return [jax_env, gym_env, ratio]


def benchmark(paths: list[Path], batches: list[int], steps: int, observation: str = "entity",
              report=lambda result: None) -> list[dict]:
    """The JAX env and the gym vector env at every batch, for every level, as result dicts (also sent to `report`)."""
    results = []
    for path in paths:
        for batch in batches:
            for result in compare(path, batch, steps, observation):
                results.append(result)
                report(result)
    final = machine_summary("gym")
    results.append(final)
    report(final)
    return results


def table_row(result: dict) -> str:
    if "peak_rss_mb" in result:
        return machine_row(result)
    head = f"{result['size']:<5}{result['level'][:23]:<24}{result['batch']:>6}  "
    if result["what"] == "gym_vs_jax":
        return f"{head}{'gym / jax':<16}{result['ratio']:>12.2f}"
    mode = "jax env (scan)" if result["what"] == "env" else f"gym vector ({result['observation']})"
    return f"{head}{mode:<16}{result['steps_per_s']:>12,.0f}{result['compile_s']:>11.2f}"


def run(args: argparse.Namespace) -> int:
    try:
        import gymnasium  # noqa: F401
    except ImportError:
        print("kinetix bench gym needs Gymnasium: pip install -e '.[gym]'", file=sys.stderr)
        return 2
    loaded = load_bench_levels(args)
    if loaded is None:
        return 2
    if args.json:
        def report(result: dict) -> None:
            print(json.dumps(result), flush=True)
    else:
        print(f"kinetix.gym vector env against the JAX env, {args.steps} agent steps per measurement (random "
              "multi-discrete actions, auto-reset); compile s: the first call (persistent cache allowed)")
        print(f"{'size':<5}{'level':<24}{'batch':>6}  {'what':<16}{'steps/s':>12}{'compile s':>11}", flush=True)

        def report(result: dict) -> None:
            print(table_row(result), flush=True)

    benchmark([path for _, _, path in loaded], args.batches, args.steps, args.observation, report)
    return 0
