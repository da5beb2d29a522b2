"""Training runs: `train_agent(...)` (a plain library call, safe to run in a worker process) and `kinetix train`.

    summary = train_agent("levels/catapult.json", "runs/catapult", steps=200_000,
                          progress=queue.put, should_stop=event.is_set)

`progress(metrics)` is called on the host after every update (metrics of kinetix.agents.ppo plus
"total_steps" and "steps_per_second"); `should_stop()` is polled between jitted chunks of updates and ends the
run early (the checkpoint is still written, marked "stopped": true). The output directory gets

    checkpoint/    the agent (kinetix.agents.checkpoint), loadable with `--agent OUT/checkpoint`
    metrics.json   {"config", "level", "curriculum", "metrics": [one dict per update], "stopped", ...}
    curve.png      mean return and solve rate against env steps
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shlex
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp

import jax2d
from kinetix.agents import checkpoint as checkpoint_module
from kinetix.agents import curricula
from kinetix.agents.checkpoint import CheckpointError
from kinetix.agents.evaluate import level_paths
from kinetix.agents.policy import resolve
from kinetix.agents.ppo import TrainConfig, make_train
from kinetix.agents.rollout import run_episodes
from kinetix.env import EnvConfig, EnvParams, make_env
from kinetix.level import WALLS_SOLVER, LevelError, size_class, solver_for
from kinetix.levels import load_level, resize
from kinetix.reset_fns import stack_levels

RANDOM_LEVELS = ("random-s", "random-m", "random-l")
RANDOM_DENSE_REWARD = 0.1  # shaping on generated levels, as the public Kinetix environment


def setup_levels(level: str, curriculum: str | None, observation: str, action: str,
                 curriculum_config: curricula.CurriculumConfig, dense_reward: float | None):
    """(env, env_params, curriculum factory taking a solve_rate_fn, description) for a --level spec."""
    if level in RANDOM_LEVELS:
        from kinetix.generate import sample_level

        size = size_class(level[-1])
        generator = lambda key: sample_level(key, size)
        # Generated levels are built on empty_level: their walls are static.
        env = make_env(EnvConfig(size, observation=observation, action=action, solver=WALLS_SOLVER), generator)
        params = EnvParams(dense_reward_scale=RANDOM_DENSE_REWARD if dense_reward is None else dense_reward)
        name = curriculum or "dr"
        if name == "dr":
            factory = lambda solve_rate_fn: curricula.domain_randomisation(generator)
        elif name == "sfl":
            factory = lambda solve_rate_fn: curricula.sfl(generator, solve_rate_fn, curriculum_config)
        elif name == "plr":
            factory = lambda solve_rate_fn: curricula.plr(generator, curriculum_config)
        else:
            raise ValueError(f"unknown curriculum {name!r}: use one of {', '.join(curricula.CURRICULA)}")
        return env, params, factory, name
    if curriculum is not None:
        raise ValueError(f"--curriculum {curriculum} needs random levels (--level random-s|random-m|random-l); "
                         f"a level file or directory is trained on as given")
    files = [load_level(p) for p in level_paths(level)]
    skips = {lf.params.frame_skip for lf in files}
    if len(skips) > 1:
        raise LevelError(f"the levels in {level} use different frame skips {sorted(skips)}; train them separately")
    largest = max((lf.size for lf in files), key=lambda s: (s.polygons + s.circles, s.joints, s.thrusters))
    files = [lf if lf.size == largest else resize(lf, largest) for lf in files]
    env = make_env(EnvConfig(largest, observation=observation, action=action, frame_skip=skips.pop(),
                             solver=solver_for([lf.level for lf in files])), files[0])
    params = EnvParams.from_level_params(files[0].params)
    if dense_reward is not None:
        params = dataclasses.replace(params, dense_reward_scale=dense_reward)
    stacked = stack_levels(files)
    return env, params, lambda solve_rate_fn: curricula.fixed(stacked), "fixed"


def train_agent(level: str, out: str | os.PathLike, *, steps: int = 1_000_000, curriculum: str | None = None,
                init: str | None = None, seed: int = 0, config: TrainConfig | None = None,
                observation: str = "entity", action: str = "multi_discrete", dense_reward: float | None = None,
                curriculum_config: curricula.CurriculumConfig | None = None, shard: bool = True,
                progress: Callable[[dict], None] | None = None, should_stop: Callable[[], bool] | None = None,
                command: str | None = None) -> dict:
    """Train, then write OUT/checkpoint, OUT/metrics.json and OUT/curve.png. Returns the metrics.json content."""
    out = Path(out)
    config = config or TrainConfig()
    config = dataclasses.replace(config, total_timesteps=steps)
    curriculum_config = curriculum_config or curricula.CurriculumConfig()
    init_params = None
    if init is not None:  # fine-tune: the network's shape comes from the checkpoint
        ckpt = checkpoint_module.load(resolve(init)) if init not in ("noop", "random") else None
        if ckpt is None:
            raise CheckpointError(f"--init {init}: only a trained agent (general or a checkpoint) can be fine-tuned")
        config = dataclasses.replace(config, network=ckpt.train_config.network, width=ckpt.train_config.width,
                                     hidden=ckpt.train_config.hidden)
        observation, action = ckpt.env["observation"], ckpt.env["action"]
        init_params = jax.tree.map(jnp.asarray, ckpt.params)
    env, env_params, factory, curriculum_name = setup_levels(level, curriculum, observation, action,
                                                             curriculum_config, dense_reward)
    if init_params is not None and ckpt.env["observation"] != "entity" and ckpt.env["size"] != env.config.size.name:
        raise CheckpointError(f"--init {init} fits size {ckpt.env['size']} only, the levels are {env.config.size.name}")

    sharder = None
    if shard and jax.device_count() > 1:
        from kinetix.agents.sharding import batch_sharder, local_mesh

        sharder = batch_sharder(local_mesh(jax.devices()), config.num_envs)  # all processes' devices

    network_holder = {}

    def solve_rate_fn(key, net_params, levels, attempts):
        from kinetix.agents import distributions

        network = network_holder["network"]
        repeated = jax.tree.map(lambda x: jnp.repeat(x, attempts, axis=0), levels)

        def act(k, obs):
            outputs, _ = network.apply({"params": net_params}, jax.tree.map(lambda x: x[None], obs))
            return distributions.sample(k, outputs, env.config.action)[0]

        solved, _ = run_episodes(env, env_params, act, repeated, key, int(env_params.max_timesteps))
        return solved.reshape(-1, attempts).mean(-1)

    trainer = make_train(config, env, env_params, factory(solve_rate_fn), init_params=init_params, shard=sharder)
    network_holder["network"] = trainer.network
    runner = jax2d.jit(trainer.init)(jax.random.key(seed))
    history: list[dict] = []
    start = time.perf_counter()
    stopped = False
    for _ in range(config.num_chunks):
        if should_stop is not None and should_stop():
            stopped = True
            break
        runner, metrics = trainer.run(runner)
        metrics = jax.device_get(metrics)
        elapsed = time.perf_counter() - start
        for i in range(config.updates_per_call):
            m = {k: float(v[i]) for k, v in metrics.items()}
            m["total_steps"] = config.planned_steps
            m["steps_per_second"] = m["env_steps"] / elapsed
            m["elapsed"] = elapsed
            history.append(m)
            if progress is not None:
                progress(m)
    train_state = runner.train_state
    info = {"level": level, "curriculum": curriculum_name, "steps": history[-1]["env_steps"] if history else 0,
            "seed": seed, "init": init, "command": command, "stopped": stopped}
    checkpoint_module.save(out / "checkpoint", train_state.params, config, env.config, info)
    summary = {"config": dataclasses.asdict(config), **info,
               "curriculum_config": (dataclasses.asdict(curriculum_config) if curriculum_name in ("sfl", "plr")
                                     else None),
               "size": env.config.size.name, "devices": jax.local_device_count(),
               "elapsed_seconds": time.perf_counter() - start, "metrics": history}
    tmp = out / "metrics.json.tmp"
    tmp.write_text(json.dumps(summary, indent=1) + "\n")
    os.replace(tmp, out / "metrics.json")
    from kinetix.agents.plot import learning_curve

    learning_curve(out / "curve.png", {Path(level).stem if level not in RANDOM_LEVELS else level: history})
    return summary


class StopRule:
    """When `kinetix train` ends early: a wall-clock budget, or a training solve rate held over recent updates.

    Polled between jitted chunks, so a run overshoots by at most one chunk. The solve rate is that of the
    episodes that finished in each update, averaged over the last `window` updates (one lucky update is not
    enough); updates where no episode finished do not count.
    """

    def __init__(self, minutes: float | None = None, target_solve_rate: float | None = None, window: int = 8):
        if minutes is not None and not minutes > 0:
            raise ValueError(f"--minutes must be positive, got {minutes}")
        if target_solve_rate is not None and not 0 < target_solve_rate <= 1:
            raise ValueError(f"--target-solve-rate must be in (0, 1], got {target_solve_rate}")
        self.minutes, self.target, self.window = minutes, target_solve_rate, window
        self.start = time.perf_counter()
        self.rates: list[float] = []
        self.reason: str | None = None

    def observe(self, metrics: dict) -> None:
        if metrics.get("episodes", 1) > 0 and metrics["solve_rate"] == metrics["solve_rate"]:  # not NaN
            self.rates.append(float(metrics["solve_rate"]))

    def __call__(self) -> bool:
        if self.minutes is not None and time.perf_counter() - self.start >= 60 * self.minutes:
            self.reason = f"time budget of {self.minutes:g} min used"
        recent = self.rates[-self.window:]
        if self.target is not None and len(recent) == self.window and sum(recent) / self.window >= self.target:
            self.reason = f"solve rate {sum(recent) / self.window:.2f} over the last {self.window} updates"
        return self.reason is not None


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    config = TrainConfig(num_envs=args.num_envs, num_steps=args.num_steps, network=args.network, lr=args.lr,
                         updates_per_call=args.updates_per_call)
    observation = args.observation or args.network
    out = Path(args.out) if args.out else Path("runs") / f"{Path(args.level).stem}-{time.strftime('%Y%m%d-%H%M%S')}"
    # smoothing=0: the rate and ETA average over the whole run (updates arrive in chunks, compile time included)
    total = dataclasses.replace(config, total_timesteps=args.steps).planned_steps
    bar = tqdm(total=total, unit="step", unit_scale=True, dynamic_ncols=True, smoothing=0, file=sys.stderr)

    try:
        rule = StopRule(args.minutes, args.target_solve_rate)
    except ValueError as error:
        bar.close()
        print(f"kinetix train: {error}", file=sys.stderr)
        return 2

    def progress(m: dict) -> None:
        rule.observe(m)
        bar.update(int(m["env_steps"]) - bar.n)
        bar.set_postfix(ret=f"{m['mean_return']:.2f}", solve=f"{m['solve_rate']:.2f}",
                        sps=f"{m['steps_per_second']:.0f}")

    command = "kinetix " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if args.record_command else None
    # The first Ctrl+C (or SIGTERM) stops after the current chunk and still writes everything; a second one aborts.
    interrupted = []

    def stop_gracefully(signum, frame):
        if interrupted:
            raise KeyboardInterrupt
        interrupted.append(signum)
        print("\nkinetix train: stopping after this chunk (again to abort without writing)", file=sys.stderr)

    previous = {sig: signal.signal(sig, stop_gracefully) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        summary = train_agent(args.level, out, steps=args.steps, curriculum=args.curriculum, init=args.init,
                              seed=args.seed, config=config, observation=observation,
                              dense_reward=args.dense_reward, shard=not args.no_shard, progress=progress,
                              should_stop=lambda: bool(interrupted) or rule(), command=command)
    except (LevelError, CheckpointError, ValueError) as error:
        bar.close()
        print(f"kinetix train: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        bar.close()
        print("kinetix train: interrupted; nothing written", file=sys.stderr)
        return 130
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    bar.close()
    if rule.reason and not interrupted:
        print(f"kinetix train: stopped early: {rule.reason}", file=sys.stderr)
    last = summary["metrics"][-1] if summary["metrics"] else {}
    print(f"wrote {out}/checkpoint, metrics.json and curve.png: {summary['steps']:.0f} steps in "
          f"{summary['elapsed_seconds']:.0f} s ({last.get('steps_per_second', 0):.0f} steps/s), last return "
          f"{last.get('mean_return', float('nan')):.3f}, solve rate {last.get('solve_rate', float('nan')):.2f}")
    return 0
