"""`python -m kinetix.bench.gpu`: a GPU session's measurements in one call (run by bench/gpu.sh).

A GPU machine is lent for minutes, so everything is planned to fit one call and to survive a failing part:

1. compile: every benchmark program (env and engine rollouts at each size and batch, the PPO chunks) is
   compiled by `--workers` child processes at once into a fresh persistent compilation cache, while
   tests/test_gpu.py runs beside them (both at a lower priority than the general agent's runs, which compile
   too). On the 2-core CPU one rollout compiles in 6-9 s; one at a time, the grid's 30-odd programs would take
   most of the call. Each program's compile time is reported as its
   worker measured it (with the others compiling beside it: an upper bound).
2. measure: one process, nothing else on the GPU but the tests if they are still running, takes each program
   from the cache and times it (kinetix.bench.engine.timed_runs: the median of 5 runs when one is short).
   First the A/B at batch 2,048, each profiled (kernels per step, time by kernel) and rerun for bitwise
   equality: skip against fixed control flow (SolverConfig.control_flow, jax2d/control.py), and env s with
   the GPU compile option given as XLA_FLAGS instead, and without CUDA graphs so that the profile sees each
   kernel and counts them per stage of the step (FLAG_VARIANTS); then the grid at s and l, `kinetix
   bench train`'s PPO chunks, and the grid at m. On an H200 (docs/gpu.md) the 25-program grid compiled in
   64 s on 12 workers and measured in 126 s; the PPO chunks' compile took 160-173 s.
3. train: the time left goes to the general agent's runs (`--train DIR ...`, resumed with `kinetix train
   --resume`); they start with the compile stage, are stopped (SIGSTOP) while the measurements run, and get
   SIGTERM at the deadline, which makes them finish their chunk and write their state.

Every result is a JSON line in OUT/results.jsonl as soon as it is measured; OUT/gpu.png plots throughput
against batch. `--quick` is the dry run for the CPU: small batches and steps, two workers, the same code.
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

SIZES = ("s", "m", "l")
BATCHES = (256, 2048, 16384, 65536)
TRAIN_ENVS = (1024, 8192)
TRAIN_SIZE = "m"  # the size of the earlier H100 PPO figures (86k env steps/s at 1,024 envs, 371k at 8,192)
QUICK_BATCHES = (16, 64)
QUICK_TRAIN_ENVS = (16,)
AB_BATCH = 2048  # the issue's furthest-behind point (s at 2,048), and l beside it
# XLA flags tried in the A/B, each in processes of their own (XLA reads XLA_FLAGS once per process). "concurrent":
# the graph's nodes scheduled by their data alone. The second GPU session measured it through XLA_FLAGS (env s
# 2,048 +16 %, env l +14 % on an H200) and jax2d.compiling now asks for it per computation, so this variant should
# measure the same as the grid's env s and l at 2,048 (else the per-computation option did not take).
# "eager": no CUDA graphs, each kernel launched on its own (slower), so that the profiler sees every kernel and
# its profile's "by_stage" gives kernels and time per stage of the step (jax2d.step's named scopes): inside a
# graph it sees only the graph's launch. The engine's per-computation graph options are removed for it through
# JAX2D_COMPILER_OPTIONS (OPTION_VARIANTS), so that XLA_FLAGS' empty list takes.
FLAG_VARIANTS = {"concurrent": "--xla_gpu_command_buffer_scheduling_mode=CONCURRENT",
                 "eager": "--xla_gpu_enable_command_buffer="}
OPTION_VARIANTS = {"eager": {"xla_gpu_enable_command_buffer": None, "xla_gpu_command_buffer_scheduling_mode": None}}
# The issue's reference table (public Kinetix 3.0.2 with Jax2D 1.0.1 on one H100, JAX 0.11.2), steps/s.
REFERENCE_H100 = {
    ("env", "l"): {256: 24.4e3, 2048: 147e3, 16384: 331e3},
    ("env", "s"): {256: 97e3, 2048: 619e3, 16384: 1.77e6},
    ("engine", "l"): {256: 49e3, 2048: 300e3, 16384: 670e3},
    ("engine", "s"): {256: 200e3, 2048: 1.27e6, 16384: 3.57e6},
}


@dataclasses.dataclass(frozen=True)
class Job:
    """One benchmark program: what ("env", "engine" or "train"), size class, batch (envs), steps per rollout
    (train: rollout length), and the solver's control flow (None: the default, "skip")."""

    what: str
    size: str
    batch: int
    steps: int
    control_flow: str | None = None
    flags: str = ""  # a named entry of FLAG_VARIANTS: XLA_FLAGS for the processes that compile and run it

    @property
    def name(self) -> str:
        flow = f"/{self.control_flow}" if self.control_flow else ""
        flags = f"+{self.flags}" if self.flags else ""
        return f"{self.what} {self.size} {self.batch}{flow}{flags}"


def rollout_steps(batch: int) -> int:
    """Steps per timed rollout: 25k-650k scene steps per run (0.1-0.4 s on an H200), long enough to be well past
    the launch of the call, short enough for the median of five at the largest batches."""
    return {256: 100, 2048: 50, 16384: 20}.get(batch, 10)


def plan(quick: bool, flows: bool = True, train: bool = True, flag_variants: bool = True,
         sizes: tuple[str, ...] = SIZES, batches: tuple[int, ...] | None = None
         ) -> tuple[list[Job], list[Job], list[Job]]:
    """(the A/B, the grid, the PPO chunks). The A/B at batch 2,048: with `flows`, skip against fixed control
    flow (SolverConfig.control_flow) for env and engine s and env l; with `flag_variants`, env s and l with each
    of FLAG_VARIANTS' XLA flags, against the grid's env s and l at the same batch. `sizes` and `batches` narrow
    the grid (a short call, e.g. the goal's points on another device kind)."""
    batches = batches or (QUICK_BATCHES if quick else BATCHES)
    ab_batch = QUICK_BATCHES[-1] if quick else AB_BATCH
    ab_sizes = (("s", ("env", "engine")),) if quick else (("s", ("env", "engine")), ("l", ("env",)))
    ab = [Job(what, size, ab_batch, rollout_steps(ab_batch), flow)
          for size, whats in ab_sizes for what in whats for flow in ("skip", "fixed")] if flows else []
    ab += [Job("env", size, ab_batch, rollout_steps(ab_batch), None, flags) for flags in FLAG_VARIANTS
           for size in ("s",) + (() if quick else ("l",))] if flag_variants else []
    # The goal's batches first (2,048 and 16,384 at s and l), so that a call cut short still has them.
    order = sorted(batches, key=lambda b: (b not in (2048, 16384), b not in (256,), b))
    grid = [Job(what, size, batch, rollout_steps(batch)) for batch in order for size in ("s", "l")
            for what in ("env", "engine") if size in sizes]
    grid += [Job(what, "m", batch, rollout_steps(batch)) for batch in order for what in ("env", "engine")
             if "m" in sizes]  # in no goal
    chunks = [Job("train", TRAIN_SIZE, envs, 16 if quick else 64)
              for envs in (QUICK_TRAIN_ENVS if quick else TRAIN_ENVS)] if train else []
    return ab, grid, chunks


# ---------------------------------------------------------------- the programs

def level_path(size: str, shared: str | None) -> Path:
    from kinetix.bench.env import REFERENCE_LEVELS, default_level_paths

    if shared:
        path = Path(shared) / REFERENCE_LEVELS[size]
        if path.is_file():
            return path
    return default_level_paths([size])[0]


def compile_job(job: Job, shared: str | None):
    """(run, compile seconds, set-up seconds, level name) of an env or engine job; run() returns the rollout's
    result asynchronously."""
    if job.what == "env":
        from kinetix.bench.env import compile_rollout
        from kinetix.levels import load_level

        path = level_path(job.size, shared)
        run, compile_s, setup_s = compile_rollout(load_level(path), job.batch, job.steps, cold=False,
                                                  control_flow=job.control_flow)
        return run, compile_s, setup_s, path.stem
    from kinetix.bench.engine import builtin_workloads, compile_rollout

    workload = builtin_workloads([job.size])[0]
    if job.control_flow:
        workload = dataclasses.replace(workload, config=dataclasses.replace(workload.config,
                                                                            control_flow=job.control_flow))
    run, compile_s, setup_s = compile_rollout(workload, job.batch, job.steps, cold=False)
    return run, compile_s, setup_s, f"built-in {job.size} scenes"


def train_job(job: Job, timed: bool) -> dict:
    from kinetix.agents.bench import measure

    return measure(job.size, job.batch, job.steps, chunks=3, updates_per_call=4, timed=timed)


# ---------------------------------------------------------------- stage 1: compile workers

def compile_worker(jobs: list[Job], shared: str | None) -> None:
    """Compile each job into the persistent cache; print one JSON line per job."""
    lower_priority()
    for job in jobs:
        start = time.perf_counter()
        try:
            if job.what == "train":
                result = train_job(job, timed=False)
                compile_s = result["first_chunk_seconds"]
            else:
                compile_s = compile_job(job, shared)[1]
            line = {"job": dataclasses.asdict(job), "compile_s": round(compile_s, 2)}
        except Exception as error:  # noqa: BLE001 - reported, and the measuring stage compiles it again
            line = {"job": dataclasses.asdict(job), "error": f"{type(error).__name__}: {error}"[:2000],
                    "seconds": round(time.perf_counter() - start, 2)}
        print(json.dumps(line), flush=True)


# Niceness of the compile workers and the tests: the general agent's training program is the call's longest compile
# (4 min 38 s on the third H200 call, beside 27 grid programs and the tests on 16 cores, which left it 10 s of
# training), and its compile is what the run's time goes to first; the grid's programs each take under a minute.
BACKGROUND_NICENESS = 10


def lower_priority() -> None:
    """Called by a compile worker at its start: below the training runs (BACKGROUND_NICENESS). (Not a Popen
    preexec_fn: that runs Python between fork and exec in a multithreaded process, which JAX warns may deadlock.)"""
    os.nice(BACKGROUND_NICENESS)


def in_background(cmd: list[str]) -> list[str]:
    """`cmd` under `nice` (below the training runs), where the system has it."""
    return ["nice", "-n", str(BACKGROUND_NICENESS), *cmd] if shutil.which("nice") else cmd


def start_workers(jobs: list[Job], workers: int, shared: str | None, log_dir: Path) -> list[subprocess.Popen]:
    """Spread the jobs, biggest first, over `workers` child processes; jobs with XLA flags go to processes of
    their own (a share of the workers as large as their share of the jobs, at least one)."""
    cost = {"train": 4, "l": 3, "m": 2, "s": 1}
    groups: dict[str, list[Job]] = {}
    for job in sorted(jobs, key=lambda j: (cost.get(j.what, 0) * 10 + cost[j.size], j.batch), reverse=True):
        groups.setdefault(job.flags, []).append(job)
    procs = []
    for flags, group in groups.items():
        count = max(1, round(workers * len(group) / len(jobs)))
        for i in range(min(count, len(group))):
            spec = json.dumps([dataclasses.asdict(j) for j in group[i::count]])
            cmd = [sys.executable, "-m", "kinetix.bench.gpu", "compile", "--jobs", spec]
            if shared:
                cmd += ["--shared", shared]
            log = open(log_dir / f"worker-{flags or 'default'}-{i}.log", "w")
            procs.append(subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, text=True, env=flag_env(flags)))
    return procs


def flag_env(flags: str) -> dict[str, str]:
    """The environment of a child process for jobs with these XLA flags (FLAG_VARIANTS, and OPTION_VARIANTS'
    overrides of jax2d's compile options)."""
    from jax2d.compiling import OPTIONS_VARIABLE

    env = dict(os.environ)
    if flags:
        env["XLA_FLAGS"] = " ".join(filter(None, (env.get("XLA_FLAGS", ""), FLAG_VARIANTS[flags])))
    if flags in OPTION_VARIANTS:
        env[OPTIONS_VARIABLE] = json.dumps(OPTION_VARIANTS[flags])
    return env


# ---------------------------------------------------------------- stage 2: measuring

def measure_job(job: Job, shared: str | None, compiled: dict, profile_dir: Path | None = None) -> dict:
    from kinetix.bench.engine import all_finite, measured_on, timed_runs

    run, load_s, setup_s, level = compile_job(job, shared)
    seconds, result, runs = timed_runs(run)
    out = {"what": job.what, "size": job.size, "batch": job.batch, "steps": job.steps,
           "control_flow": job.control_flow or "default", "level": level,
           "steps_per_s": job.batch * job.steps / seconds, "seconds": seconds, "runs": runs,
           "compile_s": compiled.get(job.name), "load_s": round(load_s, 2), "setup_s": round(setup_s, 2),
           "finite": all_finite(result), **measured_on()}
    if profile_dir is not None:  # the A/B: a profile, and whether a rerun is bitwise the same
        import jax
        import numpy as np

        again = jax.block_until_ready(run())
        out["bitwise_rerun"] = all(np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)
                                   for a, b in zip(jax.tree.leaves(result), jax.tree.leaves(again), strict=True))
        name = job.name.replace(" ", "_").replace("/", "-").replace("+", "-")
        try:
            out["profile"] = profile(run, profile_dir / name, job.steps)
        except Exception as error:  # noqa: BLE001 - the measurement stands without its profile
            out["profile"] = {"error": f"{type(error).__name__}: {error}"[:2000]}
    return out


def measure_worker(jobs: list[Job], shared: str | None, compiled: dict, profile_dir: Path) -> None:
    """measure_job for each job, one JSON line each (the A/B's jobs with XLA flags, in a process of their own)."""
    for job in jobs:
        try:
            print(json.dumps(measure_job(job, shared, compiled, profile_dir)), flush=True)
        except Exception as error:  # noqa: BLE001
            print(json.dumps({"what": "error", "job": job.name, "error": f"{type(error).__name__}: {error}"[:2000]}),
                  flush=True)


STAGE_SCOPE = re.compile(r"\b((?:jax2d|env)_[a-z_]+)")


def compiled_text(run) -> str | None:
    """The optimised HLO of the compiled program a `compile_rollout` run() calls (held in its closure), or None."""
    for cell in getattr(run, "__closure__", None) or ():
        try:
            value = cell.cell_contents
        except ValueError:  # an empty cell
            continue
        if hasattr(value, "as_text"):
            return value.as_text()
    return None


def kernel_stages(hlo_text: str) -> dict[str, str]:
    """Instruction name -> the innermost stage scope in its op name (jax2d_substeps, env_goal, ...), under the
    names a trace gives its kernels: the HLO's ("loop_add_fusion.14", CPU traces) and with '_' for '.' (GPU)."""
    stages = {}
    for line in hlo_text.splitlines():
        match = re.match(r'\s*(?:ROOT )?%?([\w.\-]+) = .*?op_name="([^"]*)"', line)
        if match:
            found = STAGE_SCOPE.findall(match[2])
            if found:
                stages[match[1]] = stages[match[1].replace(".", "_")] = found[-1]
    return stages


def by_stage(data, stages: dict[str, str], steps: int) -> dict:
    """Kernels per step and milliseconds in each stage, over every trace line, for the events named in `stages`;
    "unattributed_device_events_per_step" counts the device lines' other events (copies, graph launches, kernels
    with no scope)."""
    totals: dict[str, list[float]] = {}
    unattributed = 0
    for plane in data.planes:
        for line in plane.lines:
            for event in line.events:
                stage = stages.get(event.name)
                if stage is None:
                    unattributed += "/device:" in plane.name
                    continue
                entry = totals.setdefault(stage, [0, 0.0])
                entry[0] += 1
                entry[1] += event.duration_ns
    out = {stage: {"per_step": round(count / steps, 1), "ms": round(ns / 1e6, 3)}
           for stage, (count, ns) in sorted(totals.items(), key=lambda kv: -kv[1][1])}
    return {**out, "unattributed_device_events_per_step": round(unattributed / steps, 1)}


def profile(run, directory: Path, steps: int) -> dict:
    """One run under jax.profiler: per trace line, the events, their total time and the 12 costliest names; and
    kernels and time per stage of the step ("by_stage", from the compiled program's named scopes).

    The device lines hold the kernels (and copies) the GPU ran; the host's, the launches and waits. Inside a CUDA
    graph the profiler sees only the graph's launches: the "eager" variant (FLAG_VARIANTS) shows every kernel."""
    import jax
    from jax.profiler import ProfileData

    directory.mkdir(parents=True, exist_ok=True)
    with jax.profiler.trace(str(directory)):
        jax.block_until_ready(run())
    paths = sorted(glob.glob(str(directory / "**" / "*.xplane.pb"), recursive=True))
    if not paths:
        return {"error": "no trace written"}
    data = ProfileData.from_file(paths[-1])
    lines = []
    for plane in data.planes:
        for line in plane.lines:
            totals: dict[str, list[float]] = {}
            first, last = None, None
            for event in line.events:
                entry = totals.setdefault(event.name, [0, 0.0])
                entry[0] += 1
                entry[1] += event.duration_ns
                first = event.start_ns if first is None else min(first, event.start_ns)
                last = event.start_ns + event.duration_ns if last is None else max(last,
                                                                                   event.start_ns + event.duration_ns)
            if not totals:
                continue
            count = sum(c for c, _ in totals.values())
            busy = sum(t for _, t in totals.values())
            top = sorted(totals.items(), key=lambda kv: -kv[1][1])[:12]
            lines.append({"plane": plane.name, "line": line.name, "events": count,
                          "events_per_step": round(count / steps, 1), "busy_ms": round(busy / 1e6, 3),
                          "span_ms": round((last - first) / 1e6, 3),
                          "top": [[name[:120], c, round(t / 1e6, 3)] for name, (c, t) in top]})
    text = compiled_text(run)
    return {"steps": steps, "lines": lines,
            "by_stage": by_stage(data, kernel_stages(text), steps) if text else {"error": "no compiled program"}}


# ---------------------------------------------------------------- stage 3: the general agent's runs

def train_command(run: str, steps: int | None, extra: str = "") -> list[str]:
    """`kinetix train --resume RUN` as the GPU session runs it; extra: more of its options, one string (a GPU's
    batch: `--num-envs 4096 --num-minibatches 32`, the same 8,192 samples per minibatch as the CPU's 512 / 4)."""
    cmd = [sys.executable, "-m", "kinetix", "train", "--resume", run, "--checkpoint-every", "20"]
    if steps:  # else the run's own total (a new one would change an annealed learning rate's schedule)
        cmd += ["--steps", str(steps)]
    return cmd + shlex.split(extra)


def start_training(runs: list[str], steps: int | None, log_dir: Path, extra: str = "") -> list[subprocess.Popen]:
    procs = []
    for run in runs:
        cmd = train_command(run, steps, extra)
        procs.append(subprocess.Popen(cmd, stdout=open(log_dir / f"train-{Path(run).name}.log", "w"),
                                      stderr=subprocess.STDOUT, start_new_session=False))
    return procs


def signal_all(procs: list[subprocess.Popen], sig: int) -> None:
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(sig)


# ---------------------------------------------------------------- output

def plot(results: list[dict], path: Path) -> str:
    """Throughput against batch, env and engine side by side, one line per size (the reference's dashed)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return "matplotlib missing: no plot (python -m kinetix.bench.gpu plot RESULTS.jsonl draws it elsewhere)"
    rows = [r for r in results if r.get("what") in ("env", "engine") and r.get("control_flow") == "default"
            and "steps_per_s" in r and not r.get("xla_flags")]
    if not rows:
        return "nothing to plot"
    device = rows[0].get("device_kind", "?")
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for ax, what in zip(axes, ("env", "engine"), strict=True):
        for size, colour in zip(SIZES, ("tab:blue", "tab:orange", "tab:green"), strict=True):
            points = sorted((r["batch"], r["steps_per_s"]) for r in rows if r["what"] == what and r["size"] == size)
            if points:
                ax.plot(*zip(*points, strict=True), "o-", color=colour, label=f"{size} (ours)")
            reference = REFERENCE_H100.get((what, size))
            if reference:
                ax.plot(list(reference), list(reference.values()), "x--", color=colour, alpha=0.6,
                        label=f"{size} reference (H100)")
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xlabel("batch (parallel scenes)")
        ax.set_title(f"{what} steps/s on {device}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    axes[0].set_ylabel("steps per second")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return f"wrote {path}"


def table(results: list[dict]) -> str:
    lines = [f"{'what':<7}{'size':<5}{'batch':>7} {'flow':<6}{'steps/s':>13}{'x ref':>7}{'compile s':>10}"]
    for r in results:
        if "steps_per_s" not in r or r.get("what") not in ("env", "engine"):
            continue
        ref = REFERENCE_H100.get((r["what"], r["size"]), {}).get(r["batch"])
        ratio = f"{r['steps_per_s'] / ref:7.2f}" if ref else f"{'':>7}"
        compile_s = r.get("compile_s")
        flags = f"  {r['xla_flags']}" if r.get("xla_flags") else ""
        lines.append(f"{r['what']:<7}{r['size']:<5}{r['batch']:>7} {r['control_flow']:<6}{r['steps_per_s']:>13,.0f}"
                     f"{ratio}{compile_s if compile_s is not None else '-':>10}{flags}")
    for r in results:
        if r.get("what") == "train" and "steps_per_second" in r:
            lines.append(f"train  {r['size']:<5}{r['num_envs']:>7} PPO   {r['steps_per_second']:>13,.0f}")
    return "\n".join(lines)


# ---------------------------------------------------------------- the whole call

def main_run(args: argparse.Namespace) -> int:
    start = time.monotonic()
    deadline = start + args.budget

    def left() -> float:
        return deadline - time.monotonic()

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    logs = Path(args.logs)
    logs.mkdir(parents=True, exist_ok=True)
    results_path = out / "results.jsonl"
    results: list[dict] = []

    def record(result: dict) -> None:
        result = {"t": round(time.monotonic() - start, 1), **result}
        results.append(result)
        with results_path.open("a") as f:
            f.write(json.dumps(result) + "\n")
        brief = {k: v for k, v in result.items() if k != "profile"}
        print(json.dumps(brief), flush=True)

    import jax

    from kinetix.devices import backend_report

    record({"what": "machine", **backend_report(), "devices": [str(d) for d in jax.devices()],
            "jax": jax.__version__, "python": sys.version.split()[0]})
    ab, grid, train = plan(args.quick, flows=not args.no_flows, train=not args.no_train_bench,
                           flag_variants=not args.no_flag_variants, sizes=tuple(args.sizes),
                           batches=tuple(args.batches) if args.batches else None)

    # Stage 1: compile everything at once, tests beside; the general agent's runs start compiling too.
    stage = time.monotonic()
    workers = start_workers(ab + grid + train, args.workers, args.shared, logs)
    tests = None
    if args.tests:
        tests = subprocess.Popen(in_background([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                                                *shlex.split(args.tests)]),
                                 env={k: v for k, v in os.environ.items() if k != "JAX_PLATFORMS"},
                                 stdout=open(out / "tests.log", "w"), stderr=subprocess.STDOUT)
    trainers = start_training(args.train, args.train_steps, logs, args.train_args) if args.train else []
    compiled: dict[str, float] = {}
    for proc in workers:
        try:
            stdout, _ = proc.communicate(timeout=max(1.0, args.compile_budget - (time.monotonic() - stage)))
        except subprocess.TimeoutExpired:
            proc.kill()
            stdout, _ = proc.communicate()
        for line in stdout.splitlines():
            if line.startswith("{"):
                item = json.loads(line)
                job = Job(**item["job"])
                if "compile_s" in item:
                    compiled[job.name] = item["compile_s"]
                else:
                    record({"what": "compile_error", "job": job.name, "error": item["error"]})
    record({"what": "stage", "stage": "compile", "seconds": round(time.monotonic() - stage, 1),
            "programs": len(compiled), "workers": args.workers, "compile_s": compiled})
    # Stage 2: measure, alone on the GPU.
    signal_all(trainers, signal.SIGSTOP)
    profile_dir = logs / "profiles"
    for flags in dict.fromkeys(job.flags for job in ab if job.flags):  # each in a process with its XLA flags
        jobs = [job for job in ab if job.flags == flags]
        cmd = [sys.executable, "-m", "kinetix.bench.gpu", "measure", "--jobs",
               json.dumps([dataclasses.asdict(j) for j in jobs]), "--compiled", json.dumps(compiled),
               "--profiles", str(profile_dir)] + (["--shared", args.shared] if args.shared else [])
        try:
            child = subprocess.run(cmd, capture_output=True, text=True, env=flag_env(flags),
                                   timeout=max(1.0, min(30.0 + 15.0 * len(jobs), left() - args.reserve)))
            lines = [json.loads(line) for line in child.stdout.splitlines() if line.startswith("{")]
            for line in lines:
                record({**line, "xla_flags": FLAG_VARIANTS[flags], **(
                    {"compiler_option_overrides": OPTION_VARIANTS[flags]} if flags in OPTION_VARIANTS else {})})
            if child.returncode or not lines:
                record({"what": "error", "job": f"flags {flags}", "error": child.stderr[-2000:]})
        except subprocess.TimeoutExpired:
            record({"what": "error", "job": f"flags {flags}", "error": "timed out"})
    # The goal's sizes, then the PPO chunks, then m (in no goal): the first call ran out of time before the chunks.
    ordered = [job for job in ab if not job.flags] + [job for job in grid if job.size != "m"] + train
    for job in ordered + [job for job in grid if job.size == "m"]:
        if left() < args.reserve:
            record({"what": "skipped", "job": job.name, "why": "out of time"})
            continue
        try:
            if job.what == "train":
                record({"what": "train", **train_job(job, timed=True), "compile_s": compiled.get(job.name)})
                continue
            profiled = job in ab or (job.what, job.size, job.batch) == ("env", "s", AB_BATCH)
            record(measure_job(job, args.shared, compiled, profile_dir if profiled else None))
        except Exception as error:  # noqa: BLE001 - one failing program must not cost the rest of the call
            record({"what": "error", "job": job.name, "error": f"{type(error).__name__}: {error}"[:2000]})
    print(plot(results, out / "gpu.png"), flush=True)
    if tests is not None:  # they ran beside the compiling and, if still going, the measuring (light GPU work)
        record({"what": "stage", "stage": "tests", "running_after_measuring": tests.poll() is None})
        try:
            tests.wait(timeout=max(1.0, min(args.test_budget - (time.monotonic() - start), left() - 20)))
        except subprocess.TimeoutExpired:
            tests.kill()
        tail = (out / "tests.log").read_text(errors="replace").strip().splitlines()[-3:]
        record({"what": "tests", "returncode": tests.returncode, "tail": tail})

    # Stage 3: the time left to the general agent's runs.
    if trainers:
        signal_all(trainers, signal.SIGCONT)
        stage = time.monotonic()
        while left() > args.train_stop and any(p.poll() is None for p in trainers):
            time.sleep(1.0)
        signal_all(trainers, signal.SIGTERM)  # finish the chunk, write the state
        for proc in trainers:
            try:
                proc.wait(timeout=max(5.0, left() - 5))
            except subprocess.TimeoutExpired:
                proc.kill()
        record({"what": "training", "seconds": round(time.monotonic() - stage, 1),
                "returncodes": [p.returncode for p in trainers]})
    print(table(results), flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m kinetix.bench.gpu", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command")
    run = sub.add_parser("run", help="the whole call")
    run.add_argument("--out", required=True, help="directory for results.jsonl, gpu.png and tests.log")
    run.add_argument("--logs", required=True, help="directory for worker, training and profile logs")
    run.add_argument("--shared", help="a kinetix-levels directory holding the reference levels (s/, m/, l/)")
    run.add_argument("--quick", action="store_true", help="small batches and steps: the dry run on a CPU")
    run.add_argument("--workers", type=int, default=8, help="compile processes (default 8)")
    run.add_argument("--budget", type=float, default=470.0, help="seconds for the whole run (default 470)")
    run.add_argument("--compile-budget", type=float, default=200.0, help="seconds for stage 1 (default 200)")
    run.add_argument("--test-budget", type=float, default=400.0,
                     help="seconds from the start the tests may take (default 400)")
    run.add_argument("--reserve", type=float, default=30.0, help="seconds kept back from measuring (default 30)")
    run.add_argument("--train-stop", type=float, default=25.0,
                     help="stop the training runs this many seconds before the budget ends (default 25)")
    run.add_argument("--no-flows", action="store_true", help="leave the skip/fixed control-flow A/B out")
    run.add_argument("--no-train-bench", action="store_true", help="leave `kinetix bench train`'s chunks out")
    run.add_argument("--no-flag-variants", action="store_true", help="leave the XLA_FLAGS variants' A/B out")
    run.add_argument("--sizes", nargs="+", choices=SIZES, default=list(SIZES), help="the grid's size classes")
    run.add_argument("--batches", nargs="+", type=int, default=None,
                     help=f"the grid's batches (default {', '.join(map(str, BATCHES))}; --quick: "
                          f"{', '.join(map(str, QUICK_BATCHES))})")
    run.add_argument("--tests", default="", help="pytest's arguments, one string, run beside stage 1")
    run.add_argument("--train", nargs="*", default=[], help="run directories to resume (kinetix train --resume)")
    run.add_argument("--train-steps", type=int, default=None,
                     help="--steps for the resumed runs (default: each run's own total)")
    run.add_argument("--train-args", default="",
                     help="more `kinetix train` options for the resumed runs, one string (e.g. a GPU's batch: "
                          "'--num-envs 4096 --num-minibatches 32')")
    worker = sub.add_parser("compile", help="(internal) compile jobs into the persistent cache")
    worker.add_argument("--jobs", required=True)
    worker.add_argument("--shared")
    measuring = sub.add_parser("measure", help="(internal) measure jobs, one JSON line each")
    measuring.add_argument("--jobs", required=True)
    measuring.add_argument("--compiled", default="{}")
    measuring.add_argument("--profiles", required=True)
    measuring.add_argument("--shared")
    drawing = sub.add_parser("plot", help="draw the PNG from a results.jsonl")
    drawing.add_argument("results")
    drawing.add_argument("png")
    args = parser.parse_args(argv)

    from kinetix.jaxcache import enable_compilation_cache

    if args.command == "compile":
        enable_compilation_cache()
        compile_worker([Job(**j) for j in json.loads(args.jobs)], args.shared)
        return 0
    if args.command == "measure":
        enable_compilation_cache()
        measure_worker([Job(**j) for j in json.loads(args.jobs)], args.shared, json.loads(args.compiled),
                       Path(args.profiles))
        return 0
    if args.command == "plot":
        results = [json.loads(line) for line in Path(args.results).read_text().splitlines() if line.strip()]
        print(plot(results, Path(args.png)))
        print(table(results))
        return 0
    if args.command == "run":
        enable_compilation_cache()
        return main_run(args)
    parser.print_help()
    return 2


if __name__ == "__main__":
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    sys.exit(main())
