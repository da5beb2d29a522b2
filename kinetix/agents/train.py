"""Training runs: `train_agent(...)` (a plain library call, safe to run in a worker process) and `kinetix train`.

    summary = train_agent("levels/catapult.json", "runs/catapult", steps=200_000,
                          progress=queue.put, should_stop=event.is_set)

`progress(metrics)` is called on the host after every update (metrics of kinetix.agents.ppo plus
"total_steps" and "steps_per_second"); `should_stop()` is polled between jitted chunks of updates and ends the
run early (the checkpoint is still written, marked "stopped": true). The output directory gets

    checkpoint/    the agent (kinetix.agents.checkpoint), loadable with `--agent OUT/checkpoint`
    metrics.json   {"config", "level", "curriculum", "metrics": [one dict per update], "stopped", ...}
    curve.png      mean return and solve rate against env steps
    resume/        the whole training state, for `kinetix train --resume OUT` (kinetix.agents.resume; written by
                   `kinetix train`, and by train_agent with save_state, resume or a checkpoint cadence)
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import shlex
import signal
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import jax2d
from kinetix.agents import checkpoint as checkpoint_module
from kinetix.agents import curricula, distributions
from kinetix.agents.checkpoint import CheckpointError
from kinetix.agents.policy import resolve
from kinetix.agents.ppo import ARCHITECTURE, TrainConfig, make_train, rebase_schedule, saved_config_fields
from kinetix.agents.rollout import run_episodes
from kinetix.env import EnvParams, KinetixEnv, make_env
from kinetix.level import LevelError
from kinetix.level_source import MIXED_SIZES, RANDOM_LEVELS, level_source

# Settings a resumed run may change: its length (`--resume DIR --steps N` extends or shortens it), how each
# update cuts its batch for the gradient steps (`--update-epochs`, `--num-minibatches`), the learning rate
# (`--lr`, the rate an annealed schedule starts its line from), the entropy bonus (`--ent-coef`: a long run whose
# policy stays near uniform may lower it) and the number of environments (`--num-envs`: a bigger batch where a GPU
# is lent; the environments restart on fresh levels). Nothing carried from one update to the next depends on them
# but an annealed rate's step count, which the resume re-bases so that the rate stays that of the plan at the same
# update (ppo.rebase_schedule, train_agent); Adam's moments carry over whatever the rate.
EXTENDABLE = ("train.total_timesteps", "train.update_epochs", "train.num_minibatches", "train.lr", "train.ent_coef",
              "train.num_envs")
# TrainConfig fields a plan records where a resume changed them
PLANNED = ("update_epochs", "num_minibatches", "lr", "ent_coef", "num_envs")
# What a padded random-all run keeps when it goes on in size groups (train_agent's size_groups): all of its
# learning but the curriculum state, whose buffer holds levels padded to l
REGROUP_CARRIED = (".train_state", ".key", ".update_index")


def setup_levels(level: str, curriculum: str | None, observation: str, action: str,
                 curriculum_config: curricula.CurriculumConfig, dense_reward: float | None):
    """(env, env_params, curriculum factory taking a solve_rate_fn, description) for a --level spec."""
    if level not in RANDOM_LEVELS and curriculum is not None:
        raise ValueError(f"--curriculum {curriculum} needs random levels (--level {'|'.join(RANDOM_LEVELS)}); "
                         f"a level file or directory is trained on as given")
    source = level_source(level, dense_reward)
    config = source.env_config(observation, action)
    if not source.random:
        env = make_env(config, source.files[0])
        stacked = source.stacked
        return env, source.params, lambda solve_rate_fn: curricula.fixed(stacked), "fixed"
    generator = source.generator
    env = make_env(config, generator)
    name = curriculum or "dr"
    if name == "dr":
        factory = lambda solve_rate_fn: curricula.domain_randomisation(generator)
    elif name == "sfl":
        factory = lambda solve_rate_fn: curricula.sfl(generator, solve_rate_fn, curriculum_config)
    elif name == "plr":
        factory = lambda solve_rate_fn: curricula.plr(generator, curriculum_config)
    else:
        raise ValueError(f"unknown curriculum {name!r}: use one of {', '.join(curricula.CURRICULA)}")
    return env, source.params, factory, name


def split_evenly(total: int, parts: int, unit: int = 1) -> list[int]:
    """`total` cut into `parts` multiples of `unit`, as equal as possible (the larger ones last)."""
    units, rest = divmod(total // unit, parts)
    return [unit * (units + (i >= parts - rest)) for i in range(parts)]


def size_groups_for(config: TrainConfig, devices: int) -> list[int]:
    """How `kinetix train --level random-all` splits its envs over the size classes (MIXED_SIZES): equal groups,
    each a multiple of the device count and cut whole into the minibatches. ValueError when num_envs allows none."""
    minibatch_unit = config.num_minibatches // math.gcd(config.num_minibatches, config.num_steps)
    unit = math.lcm(devices, minibatch_unit)
    if config.num_envs % unit or config.num_envs < len(MIXED_SIZES) * unit:
        raise ValueError(f"random-all trains each size class in its own group of environments: --num-envs must be a "
                         f"multiple of {unit} (the devices and minibatches) and at least {len(MIXED_SIZES) * unit}, "
                         f"got {config.num_envs} (or give --no-size-groups)")
    return split_evenly(config.num_envs, len(MIXED_SIZES), unit)


def _group_curriculum_config(curriculum_config: curricula.CurriculumConfig, g: int) -> curricula.CurriculumConfig:
    """Group g's share of the sfl candidates and of the replay buffer (each size class keeps its own)."""
    count = len(MIXED_SIZES)
    for name, value in (("buffer size", curriculum_config.buffer_size), ("candidates", curriculum_config.candidates)):
        if value < count:
            raise ValueError(f"random-all keeps a buffer per size class: the curriculum {name} must be at least "
                             f"{count}, got {value} (or give --no-size-groups)")
    return dataclasses.replace(curriculum_config,
                               buffer_size=split_evenly(curriculum_config.buffer_size, count)[g],
                               candidates=split_evenly(curriculum_config.candidates, count)[g])


def random_all_groups(counts: list[int], curriculum: str | None, observation: str, action: str,
                curriculum_config: curricula.CurriculumConfig, dense_reward: float | None,
                solve_rate_fn_for: Callable, sharder: Callable[[int], Callable | None]) -> tuple:
    """random-all's env groups (ppo.EnvGroup), one per size class of MIXED_SIZES with `counts` envs each:
    random levels of that class, the curriculum over them with the group's share of the buffer and candidates.
    solve_rate_fn_for(env): sfl's scorer on that env; sharder(num_envs): the placement of a group's arrays."""
    from kinetix.agents.ppo import EnvGroup

    groups = []
    for g, (size, count) in enumerate(zip(MIXED_SIZES, counts, strict=True)):
        env, _, factory, _ = setup_levels(f"random-{size}", curriculum, observation, action,
                                          _group_curriculum_config(curriculum_config, g), dense_reward)
        groups.append(EnvGroup(size, env, factory(solve_rate_fn_for(env)), count, sharder(count)))
    return tuple(groups)


def sfl_scorer(env: KinetixEnv, env_params: EnvParams, network_of: Callable[[], Any],
               place_rows: Callable[[int], Callable | None]) -> Callable:
    """SFL's `solve_rate_fn(key, net_params, levels (M, ...), attempts) -> (M,)` on `env`: the current policy's
    solve rate over `attempts` sampled episodes per level. network_of(): the network (made after the curriculum
    that holds this). place_rows(rows): how to split a batch of that many rows over the devices, or None.

    Why split: the candidates are generated from replicated keys, so unsplit every device played every episode of
    the scoring (the compiled program held the whole batch on each device), and an SFL refresh is about a third of a
    random-all run's time on the CPU. Split, each device plays its share."""
    def solve_rate_fn(key, net_params, levels, attempts):
        network = network_of()
        repeated = jax.tree.map(lambda x: jnp.repeat(x, attempts, axis=0), levels)
        place = place_rows(jax.tree.leaves(repeated)[0].shape[0])
        if place is not None:
            repeated = place(repeated)

        def act(k, obs):
            outputs, _ = network.apply({"params": net_params}, jax.tree.map(lambda x: x[None], obs))
            return distributions.sample(k, outputs, env.config.action)[0]

        solved, _ = run_episodes(env, env_params, act, repeated, key, int(env_params.max_timesteps))
        return solved.reshape(-1, attempts).mean(-1)

    return solve_rate_fn


def train_agent(level: str, out: str | os.PathLike, *, steps: int = 1_000_000, curriculum: str | None = None,
                init: str | None = None, seed: int = 0, config: TrainConfig | None = None,
                observation: str = "entity", action: str = "multi_discrete", dense_reward: float | None = None,
                curriculum_config: curricula.CurriculumConfig | None = None, shard: bool = True,
                progress: Callable[[dict], None] | None = None, should_stop: Callable[[], bool] | None = None,
                command: str | None = None, resume: bool = False, checkpoint_every: float | None = None,
                checkpoint_every_updates: int | None = None, save_state: bool = False,
                size_groups: bool | None = None) -> dict:
    """Train, then write OUT/checkpoint, OUT/metrics.json, OUT/curve.png and OUT/resume/. Returns the metrics.json
    content.

    save_state: also write the whole training state to OUT/resume (kinetix.agents.resume) at the end, stopped early
    or not, so the run can be resumed (`kinetix train` always does; off by default for library callers such as the
    server, whose specialists need only the checkpoint). resume: continue the run whose training state is in
    OUT/resume instead of starting afresh; every setting but `steps`, `config.update_epochs`,
    `config.num_minibatches`, `config.lr`, `config.ent_coef` and `config.num_envs` must equal the saved run's
    (CheckpointError naming
    the differences otherwise). A different `steps` re-plans the run (longer or shorter, not shorter than what is
    done): an annealed learning rate is from then on that of a `steps`-long run at the same update (it jumps where
    the plan changes; a finished run's 0 becomes lr * (1 - done / steps)), and with a constant one the result equals
    a run planned that long from the start. Different epochs or minibatches cut the updates from then on
    differently; the rate stays lr * (1 - update / updates planned). A different `config.lr` holds from the resume
    on: an annealed rate is then the new lr's line at the same update. A different `config.ent_coef` weighs the
    entropy bonus from the resume on. A different `config.num_envs` (a bigger batch
    on a GPU) carries the learning and the curriculum's buffer over and starts every environment on a fresh level
    (as a compact state does), random-all's size groups cut afresh; the run goes on to `steps` env steps in updates
    of the new batch (the plan records the env steps done where it changed, so a later resume counts them), with an
    annealed rate re-based as for a new length. checkpoint_every (minutes of wall-clock time) /
    checkpoint_every_updates: also write everything between chunks at that cadence, so a killed job loses at most
    that much work. Either of these implies save_state. In a multi-process run only process 0 writes.

    size_groups (random-all only): step each size class's levels in its own group of environments at its own size
    (ppo.EnvGroup; a third of the envs each, every group with its own curriculum and a third of its buffer and sfl
    candidates) instead of padding every level to l in one batch. The default: on for new random-all runs (not
    with flat observations, whose length depends on the size), and for a resumed run whatever it was saved with."""
    from kinetix.agents import multihost
    from kinetix.agents import resume as resume_module

    for name, value in (("checkpoint_every", checkpoint_every), ("checkpoint_every_updates", checkpoint_every_updates)):
        if value is not None and not value > 0:
            raise ValueError(f"{name.replace('_', '-')} must be positive, got {value}")
    out = Path(out)
    save_state = save_state or resume or checkpoint_every is not None or checkpoint_every_updates is not None
    config = config or TrainConfig()
    config = dataclasses.replace(config, total_timesteps=steps)
    curriculum_config = curriculum_config or curricula.CurriculumConfig()
    init_params = None
    if init is not None:  # fine-tune: the network's shape comes from the checkpoint
        ckpt = checkpoint_module.load(resolve(init)) if init not in ("noop", "random") else None
        if ckpt is None:
            raise CheckpointError(f"--init {init}: only a trained agent (general or a checkpoint) can be fine-tuned")
        config = dataclasses.replace(config, **{field: getattr(ckpt.train_config, field) for field in ARCHITECTURE})
        observation, action = ckpt.env["observation"], ckpt.env["action"]
        init_params = jax.tree.map(jnp.asarray, ckpt.params)
    env, env_params, factory, curriculum_name = setup_levels(level, curriculum, observation, action,
                                                             curriculum_config, dense_reward)
    if init_params is not None and ckpt.env["observation"] != "entity" and ckpt.env["size"] != env.config.size.name:
        raise CheckpointError(f"--init {init} fits size {ckpt.env['size']} only, the levels are {env.config.size.name}")
    saved = resume_module.load_latest(out) if resume else None
    history: list[dict] = []
    elapsed_before = 0.0
    plans = [{"update": 0, "steps": steps}]  # the run's length and batch cut, and where a --resume changed them
    steps_offset = 0  # env steps done before the batch size in force, beyond its update count's
    resized = False
    if saved is not None:
        history, elapsed_before = list(saved[0]["history"]), float(saved[0]["elapsed"])
        plans = replan(saved[0], len(history), steps, {k: getattr(config, k) for k in PLANNED})
        # resumed with another number of environments: its learning and curriculum carry over, its environments
        # restart on fresh levels, and its size groups are cut afresh
        resized = saved[0]["run"]["train"]["num_envs"] != config.num_envs
        if resized:
            plans[-1] = {**plans[-1], "env_steps": history[-1]["env_steps"] if history else 0}
        steps_offset = batch_offset(plans, config)
        if steps_offset:  # the plans count env steps; the loop and the schedule count updates of this batch
            # (at least one: a length below what is done is refused below, as for any resume)
            config = dataclasses.replace(config, total_timesteps=max(1, steps - steps_offset))
    saved_groups = saved is not None and bool(saved[0]["run"].get("size_groups"))
    if size_groups is None:
        size_groups = saved_groups if saved is not None else level == "random-all" and observation != "flat"
    # a random-all run padded to l, resumed with size_groups=True, goes on in groups: its learning carries over
    # (parameters, optimiser, key, update index); its environments and curriculum buffer start afresh
    regroup = saved is not None and size_groups and not saved_groups
    if size_groups and level != "random-all":
        raise ValueError(f"size groups are for --level random-all, not {level}")
    if size_groups and observation == "flat":
        raise ValueError("flat observations differ in length between size classes: train random-all with them "
                         "padded to l (--no-size-groups)")

    if not shard and jax.process_count() > 1:
        raise ValueError("--no-shard cannot be used with several processes: each would train the whole batch alone")
    mesh = None
    if shard and jax.device_count() > 1 and (jax.process_count() > 1 or config.num_envs % jax.device_count() == 0):
        # (one process with a batch its devices do not divide trains on one device, as kinetix.devices.batch_devices)
        from kinetix.agents.sharding import local_mesh

        mesh = local_mesh(jax.devices())  # all processes' devices
    group_sizes = None
    if size_groups and saved_groups and not resized:  # a run's groups are part of it, whatever the devices
        group_sizes = [saved[0]["run"]["size_groups"][size] for size in MIXED_SIZES]
        if mesh is not None and any(n % jax.device_count() for n in group_sizes):
            if jax.process_count() > 1:
                raise ValueError(f"the run's size groups {group_sizes} do not split over {jax.device_count()} devices")
            mesh = None  # as above: one device when they do not divide
    elif size_groups:
        try:
            group_sizes = size_groups_for(config, 1 if mesh is None else jax.device_count())
        except ValueError:
            if mesh is None or jax.process_count() > 1:
                raise
            mesh, group_sizes = None, size_groups_for(config, 1)  # as above: one device when they do not divide
    run_id = run_identity(level, config, curriculum_name, curriculum_config, seed, init, env, env_params, factory)
    if group_sizes is not None:
        run_id["size_groups"] = dict(zip(MIXED_SIZES, group_sizes, strict=True))
    if saved is not None:
        saved_run = {**saved[0]["run"], "train": saved_config_fields(saved[0]["run"]["train"])}
        resume_module.compare_runs(saved_run, run_id,
                                   ignore=EXTENDABLE + (("size_groups",) if regroup or resized else ()))

    def sharder(num_envs: int):
        from kinetix.agents.sharding import batch_sharder

        return None if mesh is None else batch_sharder(mesh, num_envs)

    network_holder = {}

    def place_rows(rows: int) -> Callable | None:
        return sharder(rows) if mesh is not None and rows % jax.device_count() == 0 else None

    def solve_rate_fn_for(env):
        return sfl_scorer(env, env_params, lambda: network_holder["network"], place_rows)

    groups = None
    if group_sizes is not None:
        groups = random_all_groups(group_sizes, curriculum, observation, action, curriculum_config, dense_reward,
                                   solve_rate_fn_for, sharder)
    trainer = make_train(config, env, env_params, factory(solve_rate_fn_for(env)), init_params=init_params,
                         shard=sharder(config.num_envs), groups=groups)
    network_holder["network"] = trainer.network
    runner = jax2d.jit(trainer.init)(jax.random.key(seed))
    if saved is not None:
        meta, arrays, _ = saved
        if resized:
            if group_sizes is not None:
                plans[-1] = {**plans[-1], "size_groups": run_id["size_groups"]}
            arrays = resume_module.compact(arrays)  # the environments restart, at the new count
            warnings.warn(f"{out}: from update {len(history)} on with {config.num_envs} environments (was "
                          f"{saved[0]['run']['train']['num_envs']}): every environment restarts on a fresh level",
                          stacklevel=2)
        if len(history) % config.updates_per_call:
            raise CheckpointError(f"the training state in {out} holds {len(history)} updates, not a whole number of "
                                  f"this run's chunks")
        if len(history) > config.num_chunks * config.updates_per_call:
            raise CheckpointError(f"the run in {out} has trained {history[-1]['env_steps']:.0f} steps already; "
                                  f"--steps {steps} would end before that (give at least that many to extend it)")
        if regroup:
            if plans[-1]["update"] != len(history):
                plans.append({"update": len(history), "steps": steps})
            plans[-1] = {**plans[-1], "size_groups": run_id["size_groups"]}  # where the run went on in groups
            fresh = {path: array for path, array in resume_module.flatten(resume_module.host_tree(runner)).items()
                     if path.startswith(".curriculum")}  # the groups' own empty buffers
            arrays = {**fresh, **{path: array for path, array in arrays.items() if path.startswith(REGROUP_CARRIED)}}
            warnings.warn(f"{out}: from update {len(history)} on in size groups {run_id['size_groups']}; the "
                          f"environments and the curriculum's buffer start afresh", stacklevel=2)
        runner = resume_module.restore(runner, arrays)
        runner = dataclasses.replace(runner, train_state=rebase_schedule(runner.train_state, config, len(history)))
        if resume_module.is_compact(arrays):  # fresh environments: their levels are no buffer slot's (-2)
            runner = dataclasses.replace(runner, env_level_ids=jax.tree.map(lambda ids: ids * 0 - 2,
                                                                            runner.env_level_ids))
            if not (regroup or resized):  # (which said so already)
                warnings.warn(f"{out}: a compact training state; every environment restarts on a fresh level",
                              stacklevel=2)
    start = time.perf_counter()
    arguments = {"level": level if level in RANDOM_LEVELS else str(Path(level).resolve()), "steps": steps,
                 "curriculum": curriculum, "init": init, "seed": seed, "observation": observation, "action": action,
                 "dense_reward": dense_reward, "config": dataclasses.asdict(config),
                 "curriculum_config": dataclasses.asdict(curriculum_config)}

    def write(stopped: bool, final: bool) -> dict:
        """Everything a finished run leaves (the curve only at the end); a collective in multi-process runs."""
        host = resume_module.host_tree(runner if save_state else runner.train_state.params)
        elapsed = elapsed_before + time.perf_counter() - start
        info = {"level": level, "curriculum": curriculum_name, "steps": history[-1]["env_steps"] if history else 0,
                "seed": seed, "init": init, "command": command, "stopped": stopped}
        summary = {"config": dataclasses.asdict(config), **info,
                   "curriculum_config": (dataclasses.asdict(curriculum_config) if curriculum_name in ("sfl", "plr")
                                         else None),
                   "size": env.config.size.name, "size_groups": run_id.get("size_groups"),
                   "devices": jax.device_count(), "processes": jax.process_count(),
                   "resumed_at_update": None if saved is None else len(saved[0]["history"]), "plans": plans,
                   "complete": len(history) == config.num_chunks * config.updates_per_call,  # False mid-run
                   "elapsed_seconds": elapsed, "metrics": history}
        if not multihost.is_main():
            return summary
        if save_state:
            meta = {"run": run_id, "arguments": arguments, "history": history, "elapsed": elapsed, "plans": plans}
            resume_module.save(out, len(history), meta, resume_module.flatten(host))
        params = host.train_state.params if save_state else host
        checkpoint_module.save(out / "checkpoint", params, config, env.config, info)
        tmp = out / "metrics.json.tmp"
        tmp.write_text(json.dumps(summary, indent=1) + "\n")
        os.replace(tmp, out / "metrics.json")
        if final:
            from kinetix.agents.plot import learning_curve

            learning_curve(out / "curve.png", {Path(level).stem if level not in RANDOM_LEVELS else level: history})
        return summary

    runner = settled(runner)
    stopped = False
    if len(history) < config.num_chunks * config.updates_per_call:  # processes compile at different speeds:
        multihost.compile_together(trainer.run, runner)  # they meet before the update's collectives
    last_save_time, last_save_update = time.perf_counter(), len(history)
    for _ in range(len(history) // config.updates_per_call, config.num_chunks):
        stop = should_stop is not None and should_stop()
        due = checkpoint_due(time.perf_counter() - last_save_time, len(history) - last_save_update,
                             checkpoint_every, checkpoint_every_updates)
        stop, due = multihost.agree(stop, due)  # process 0 decides, so every process takes the same path
        if stop:
            stopped = True
            break
        if due:
            write(stopped=False, final=False)
            last_save_time, last_save_update = time.perf_counter(), len(history)
        runner, metrics = trainer.run(runner)
        metrics = jax.device_get(metrics)
        elapsed = elapsed_before + time.perf_counter() - start
        for i in range(config.updates_per_call):
            m = {k: float(v[i]) for k, v in metrics.items()}
            m["env_steps"] += steps_offset
            m["total_steps"] = config.planned_steps + steps_offset
            m["steps_per_second"] = m["env_steps"] / elapsed
            m["elapsed"] = elapsed
            history.append(m)
            if progress is not None:
                progress(m)
    return write(stopped=stopped, final=True)


def settled(runner: Any) -> Any:
    """`runner` with every leaf strongly typed and committed to its sharding, as `resume.restore` returns it.

    Why: the chunk program is compiled for its arguments' types and placements, and the persistent compilation
    cache keys on the lowered program. A fresh runner holds weakly typed scalars (the step count, the env params'
    Python floats) and uncommitted arrays; a restored one holds neither. Unsettled, every `--resume` compiled its
    chunk program afresh instead of finding the first sitting's in the cache: 132 s on this 2-core machine for a
    random-all SFL run of 4 envs at a constant rate, 19 s for levels/cartpole.json (the same numbers either way:
    only the program's argument attributes differed)."""
    def settle(leaf):
        strong = jnp.asarray(leaf, dtype=leaf.dtype) if getattr(leaf, "weak_type", False) else leaf
        return jax.device_put(strong, leaf.sharding)

    return jax.tree.map(settle, runner)


def batch_offset(plans: list[dict], config: TrainConfig) -> int:
    """Env steps the run did beyond `config`'s batch size times its update count: 0 unless a resume changed the
    number of environments (the latest such plan records the env steps done where it did, "env_steps")."""
    for plan in reversed(plans):
        if "env_steps" in plan:
            return int(plan["env_steps"]) - plan["update"] * config.batch_size
    return 0


def replan(meta: dict, done: int, steps: int, settings: dict | None = None) -> list[dict]:
    """The saved run's plans ({"update", "steps"}: its length from that update on; with every PLANNED field,
    "update_epochs", "num_minibatches", "lr", "ent_coef" and "num_envs", where one of them changed there), with
    `steps` and `settings` (PLANNED TrainConfig fields) from update `done` on where they differ from the plans in
    force. States written before plans were recorded had one plan."""
    plans = list(meta.get("plans") or [{"update": 0, "steps": meta["arguments"]["steps"]}])
    in_force = {k: meta.get("arguments", {}).get("config", {}).get(k) for k in PLANNED}
    for plan in plans:
        in_force.update({k: plan[k] for k in PLANNED if k in plan})
    given = {k: v for k, v in (settings or {}).items() if k in PLANNED}
    changed = {k: v for k, v in given.items() if v != in_force.get(k)}
    if plans[-1]["steps"] != steps or changed:
        recorded = {k: v for k, v in {**in_force, **given}.items() if v is not None}  # (old states: no lr)
        entry = {"update": done, "steps": steps, **(recorded if changed else {})}
        if plans[-1]["update"] == done:  # re-planned again before any update ran: the newer plan replaces it
            previous = plans.pop()
            if not changed and any(k in previous for k in PLANNED):
                entry.update({k: previous[k] for k in PLANNED if k in previous})
            entry.update({k: previous[k] for k in ("env_steps", "size_groups") if k in previous})
        plans.append(entry)
    return plans


def checkpoint_due(seconds_since: float, updates_since: int, every_minutes: float | None,
                   every_updates: int | None) -> bool:
    """Whether the periodic checkpoint is due, `seconds_since` / `updates_since` the last one (or the job's start)."""
    return bool((every_minutes is not None and seconds_since >= 60 * every_minutes)
                or (every_updates is not None and updates_since >= every_updates))


def run_identity(level: str, config: TrainConfig, curriculum_name: str, curriculum_config: curricula.CurriculumConfig,
                 seed: int, init: str | None, env, env_params: EnvParams, factory) -> dict:
    """What defines a run's numbers: a resumed run must match the saved one in all of it. Level files count by
    content (a digest of the stacked levels and the env params), not by path, so a run can resume from another
    working directory but not on edited levels."""
    digest = hashlib.sha256()
    for leaf in jax.tree.leaves(env_params):
        digest.update(np.asarray(leaf).tobytes())
    if curriculum_name == "fixed":
        for leaf in jax.tree.leaves(factory(None).init(None)):  # the stacked levels
            digest.update(np.asarray(leaf).tobytes())
    return {"train": dataclasses.asdict(config), "curriculum": curriculum_name, "seed": seed, "init": init,
            "curriculum_config": dataclasses.asdict(curriculum_config) if curriculum_name in ("sfl", "plr") else None,
            "env": checkpoint_module.env_description(env.config),
            "levels": (level if level in RANDOM_LEVELS else "files") + " sha256:" + digest.hexdigest()[:16]}


DEAD_WARNING = 0.5  # actor_dead (ppo_loss) from which `kinetix train` warns, once per sitting


def dead_actor_warning(metrics: dict, activation: str) -> str | None:
    """The warning for an update whose actor has a layer at least DEAD_WARNING dead, else None. Why it matters: the
    first general run's actor died that way unnoticed (kinetix.agents.networks); only its entropy showed it, late."""
    share = metrics.get("actor_dead", 0.0)
    if not share >= DEAD_WARNING:
        return None
    recovers = "relu units dead on every input do not recover" if activation == "relu" else "saturated tanh units"
    return (f"kinetix train: update {metrics['update']:.0f}: {share:.0%} of the units of one of the actor's hidden "
            f"layers passed no gradient on its minibatches ({recovers}); its policy is losing its dependence on the "
            f"state. Measure a checkpoint with python -m kinetix.agents.health")


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


# `kinetix train` options that are TrainConfig fields of the same name
CONFIG_OPTIONS = ("num_envs", "num_steps", "updates_per_call", "lr", "ent_coef", "network", "width", "hidden",
                  "update_epochs", "num_minibatches", "activation", "pooled_norm", "gamma", "gae_lambda")


def settings_from_args(args: argparse.Namespace) -> dict:
    """train_agent's arguments from the command line. With --resume, a setting not given is the saved run's (the
    newest intact state's "arguments"); one given is kept, and train_agent refuses it if it differs."""
    from kinetix.agents import resume as resume_module

    stored: dict = {}
    if args.resume:
        if args.out and Path(args.out).resolve() != Path(args.resume).resolve():
            raise ValueError(f"--out {args.out} differs from --resume {args.resume}: a resumed run writes where it was")
        stored = resume_module.load_latest(args.resume)[0]["arguments"]
    saved_config = {k: v for k, v in stored.get("config", {}).items() if k != "total_timesteps"}
    if saved_config:
        saved_config = saved_config_fields(saved_config)
    given_config = {k: getattr(args, k) for k in CONFIG_OPTIONS if getattr(args, k) is not None}
    if getattr(args, "constant_lr", None):
        given_config["anneal_lr"] = False
    config = TrainConfig(**{**saved_config, **given_config})

    def pick(name: str, default=None):
        value = getattr(args, name, None)
        return value if value is not None else stored.get(name, default)

    level = pick("level")
    if level is None:
        raise ValueError("--level is required (or --resume DIR to continue a run)")
    settings = {"level": level, "steps": pick("steps", 1_000_000), "curriculum": pick("curriculum"),
                "init": pick("init"), "seed": pick("seed", 0), "config": config,
                "observation": pick("observation", config.network), "action": stored.get("action", "multi_discrete"),
                "dense_reward": pick("dense_reward"), "resume": bool(args.resume),
                "size_groups": getattr(args, "size_groups", None)}
    curriculum_config = dict(stored.get("curriculum_config") or {})
    for option, field in (("sfl_refresh_every", "refresh_every"), ("sfl_candidates", "candidates"),
                          ("sfl_attempts", "attempts"), ("buffer_size", "buffer_size")):
        if getattr(args, option, None) is not None:
            curriculum_config[field] = getattr(args, option)
    if curriculum_config:
        settings["curriculum_config"] = curricula.CurriculumConfig(**curriculum_config)
    return settings


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from kinetix.agents import multihost

    try:  # before anything starts JAX's backend
        multihost.initialize(args.coordinator, args.num_processes, args.process_id)
        settings = settings_from_args(args)
        rule = StopRule(args.minutes, args.target_solve_rate)
    except (CheckpointError, ValueError, RuntimeError) as error:
        print(f"kinetix train: {error}", file=sys.stderr)
        return 2
    main = multihost.is_main()
    level, config = settings["level"], settings["config"]
    out = (Path(args.resume) if args.resume else Path(args.out) if args.out
           else Path("runs") / f"{Path(level).stem}-{time.strftime('%Y%m%d-%H%M%S')}")
    # smoothing=0: the rate and ETA average over the whole run (updates arrive in chunks, compile time included)
    total = dataclasses.replace(config, total_timesteps=settings["steps"]).planned_steps
    bar = tqdm(total=total, unit="step", unit_scale=True, dynamic_ncols=True, smoothing=0, file=sys.stderr,
               disable=not main)

    warned = []

    def progress(m: dict) -> None:
        rule.observe(m)
        bar.update(int(m["env_steps"]) - bar.n)
        bar.set_postfix(ret=f"{m['mean_return']:.2f}", solve=f"{m['solve_rate']:.2f}",
                        sps=f"{m['steps_per_second']:.0f}", kl=f"{m.get('approx_kl', 0.0):.4f}",
                        dead=f"{m.get('actor_dead', 0.0):.0%}")
        warning = None if warned or not main else dead_actor_warning(m, config.activation)
        if warning:
            warned.append(m["update"])
            tqdm.write(warning, file=sys.stderr)

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
        summary = train_agent(out=out, shard=not args.no_shard, progress=progress,
                              should_stop=lambda: bool(interrupted) or rule(), command=command,
                              checkpoint_every=args.checkpoint_every,
                              checkpoint_every_updates=args.checkpoint_every_updates, save_state=True,
                              **settings)
    except (LevelError, CheckpointError, ValueError) as error:
        bar.close()
        print(f"kinetix train: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        bar.close()
        print("kinetix train: interrupted; nothing more written (periodic checkpoints are kept)", file=sys.stderr)
        return 130
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    bar.close()
    if not main:
        return 0
    if rule.reason and not interrupted:
        print(f"kinetix train: stopped early: {rule.reason}", file=sys.stderr)
    last = summary["metrics"][-1] if summary["metrics"] else {}
    print(f"wrote {out}/checkpoint, metrics.json and curve.png: {summary['steps']:.0f} steps in "
          f"{summary['elapsed_seconds']:.0f} s ({last.get('steps_per_second', 0):.0f} steps/s), last return "
          f"{last.get('mean_return', float('nan')):.3f}, solve rate {last.get('solve_rate', float('nan')):.2f}")
    return 0
