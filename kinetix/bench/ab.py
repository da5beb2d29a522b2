"""Before against after in one process: an older commit's jax2d and kinetix beside this tree's, timed alternately.

Why one process: on the 2-core development machine the same compiled program ran up to 45 % apart between
processes, for minutes at a time (docs/engine.md, "What this round can and cannot say"), so separate processes
in ABBA order could not resolve differences under about 10 %. Here the older tree is exported from git
(`git archive`) and imported under renamed packages (`jax2d_before`, `kinetix_before`), each workload is
compiled once per side by that side's own bench code (`kinetix.bench.env.measure_rollout` and
`kinetix.bench.engine.measure_rollout`, so each side builds its environment and scenes as its own `kinetix
bench` does), and then the two compiled rollouts run in turns, round after round, the side that goes first
alternating. A slow period then hits both sides of a round, and the round's ratio (after / before) cancels it.

    python -m kinetix.bench.ab --before f3c978a --env s:16,s:256,l:1 --engine m:256,l:256 --rounds 9

Prints, per workload, both sides' median steps/s and the median and range of the per-round ratios; `--json`
prints one JSON object per workload instead. Env workloads step the issue's reference levels
(../shared/kinetix-levels, or `--level SIZE=FILE`); engine workloads the bench's built-in scenes.
Only what both trees' bench modules offer under the same names can be compared (both have had
`measure_rollout` with these arguments since before f3c978a).
"""

from __future__ import annotations

import argparse
import importlib
import io
import json
import re
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any
from unittest import mock

from kinetix.bench.env import REFERENCE_LEVELS, REPO_DIR, SHARED_LEVELS

PACKAGES = ("jax2d", "kinetix")
SUFFIX = "_before"
DEFAULT_ROUNDS = 9
DEFAULT_STEPS = 200
_IMPORT = re.compile(r"^(\s*)import (jax2d|kinetix)\s*$", re.MULTILINE)
_FROM = re.compile(r"\bfrom (jax2d|kinetix)(?=[.\s])")


def rename_imports(source: str, suffix: str = SUFFIX) -> str:
    """A module's source with its absolute imports of jax2d and kinetix pointed at the renamed packages.

    `import jax2d` becomes `import jax2d_before as jax2d` (so `jax2d.step(...)` below it still reads), and `from
    kinetix.env import x` becomes `from kinetix_before.env import x`. Dotted names in strings stay (a "from kinetix"
    in a comment or docstring is renamed too, which nothing reads).
    Both trees import these packages only in these two forms (no `import kinetix.env`, no import_module of a
    dotted name on the paths the bench runs); anything else fails loudly at import, not silently.
    """
    source = _IMPORT.sub(lambda m: f"{m.group(1)}import {m.group(2)}{suffix} as {m.group(2)}", source)
    return _FROM.sub(lambda m: f"from {m.group(1)}{suffix}", source)


def export_tree(commit: str, dest: Path, repo: Path = REPO_DIR, suffix: str = SUFFIX) -> Path:
    """Write `commit`'s jax2d/, kinetix/ and levels/ under dest, the packages renamed; returns dest."""
    try:
        archive = subprocess.run(["git", "-C", str(repo), "archive", "--format=tar", commit, *PACKAGES, "levels"],
                                 check=True, capture_output=True).stdout
    except subprocess.CalledProcessError as error:
        raise SystemExit(f"git archive {commit} failed: {error.stderr.decode().strip()}") from None
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(dest, filter="data")
    for package in PACKAGES:
        renamed = dest / f"{package}{suffix}"
        (dest / package).rename(renamed)
        for path in renamed.rglob("*.py"):
            path.write_text(rename_imports(path.read_text(), suffix))
    return dest


class Side:
    """One tree's bench modules and level loader, imported under its own package names."""

    def __init__(self, prefix: str):
        self.env = importlib.import_module(f"kinetix{prefix}.bench.env")
        self.engine = importlib.import_module(f"kinetix{prefix}.bench.engine")
        self.levels = importlib.import_module(f"kinetix{prefix}.levels")

    def compiled(self, what: str, size: str, batch: int, steps: int, level: Path | None) -> Callable[[], Any]:
        """An argument-free call that runs the workload's compiled rollout (its first run already done)."""
        module = self.env if what == "env" else self.engine
        captured = []

        def capture(run):  # stands in for the bench's timed_runs: keep the call, run it once for the result
            import jax

            captured.append(run)
            return 1.0, jax.block_until_ready(run()), 1

        with mock.patch.object(module, "timed_runs", capture):
            if what == "env":
                module.measure_rollout(self.levels.load_level(level), level.stem, batch, steps, cold=False)
            else:
                (workload,) = self.engine.builtin_workloads([size])
                module.measure_rollout(workload, batch, steps, cold=False)
        return captured[0]


def _time(run: Callable[[], Any]) -> float:
    import jax

    start = time.perf_counter()
    jax.block_until_ready(run())
    return time.perf_counter() - start


def alternate(before: Callable[[], Any], after: Callable[[], Any], rounds: int) -> tuple[list[float], list[float]]:
    """Seconds of each side's run, round by round; the side that runs first alternates between rounds."""
    times: dict[str, list[float]] = {"before": [], "after": []}
    for r in range(rounds):
        order = (("before", before), ("after", after)) if r % 2 == 0 else (("after", after), ("before", before))
        for name, run in order:
            times[name].append(_time(run))
    return times["before"], times["after"]


def summary(what: str, size: str, batch: int, steps: int, before_s: list[float], after_s: list[float]) -> dict:
    """Median steps/s of each side, the per-round ratios (after's speed over before's), and the ratio of each
    side's fastest run ("ratio_best"): interference only slows a run, so the fastest is the nearest to the
    program's own speed, and on a machine with slow periods the two measures disagree less than single rounds."""
    ratios = [b / a for b, a in zip(before_s, after_s, strict=True)]
    return {
        "what": what, "size": size, "batch": batch, "steps": steps, "rounds": len(ratios),
        "before_steps_per_s": batch * steps / statistics.median(before_s),
        "after_steps_per_s": batch * steps / statistics.median(after_s),
        "ratio_median": statistics.median(ratios), "ratio_min": min(ratios), "ratio_max": max(ratios),
        "ratio_best": min(before_s) / min(after_s),
        "ratios": ratios,
    }


def parse_workloads(text: str, sizes: tuple[str, ...] = ("s", "m", "l")) -> list[tuple[str, int]]:
    """"s:16,l:1" -> [("s", 16), ("l", 1)]; a clear error for anything else."""
    workloads = []
    for item in filter(None, text.split(",")):
        size, _, batch = item.partition(":")
        if size not in sizes or not batch.isdigit() or int(batch) < 1:
            raise argparse.ArgumentTypeError(
                f"{item!r}: expected SIZE:BATCH with SIZE one of {', '.join(sizes)} and BATCH >= 1")
        workloads.append((size, int(batch)))
    return workloads


def parse_engine_workloads(text: str) -> list[tuple[str, int]]:
    """As parse_workloads, with xl too: the engine has a built-in xl scene, the env no reference xl level."""
    return parse_workloads(text, ("s", "m", "l", "xl"))


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m kinetix.bench.ab", description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", required=True, help="the commit to compare this tree against")
    parser.add_argument("--env", type=parse_workloads, default=[], metavar="SIZE:BATCH,...",
                        help="env rollouts (agent steps), e.g. s:16,s:256,l:1")
    parser.add_argument("--engine", type=parse_engine_workloads, default=[], metavar="SIZE:BATCH,...",
                        help="engine rollouts of the bench's built-in scenes (physics steps), xl included")
    parser.add_argument("--rounds", type=int, default=DEFAULT_ROUNDS, help="timed runs per side and workload")
    parser.add_argument("--steps", type=int, default=DEFAULT_STEPS, help="steps per rollout")
    parser.add_argument("--level", action="append", default=[], metavar="SIZE=FILE",
                        help="the env level of a size class (default: the reference level in ../shared)")
    parser.add_argument("--devices", type=int, default=None, help="CPU devices to split a batch over (default: cores)")
    parser.add_argument("--json", action="store_true", help="one JSON object per workload")
    args = parser.parse_args(argv)
    if not args.env and not args.engine:
        parser.error("nothing to measure: give --env and/or --engine")
    if args.rounds < 1 or args.steps < 1:
        parser.error("--rounds and --steps must be at least 1")
    levels = {size: SHARED_LEVELS / name for size, name in REFERENCE_LEVELS.items()}
    for item in args.level:
        size, _, path = item.partition("=")
        if size not in levels or not Path(path).is_file():
            parser.error(f"--level {item!r}: expected SIZE=FILE with SIZE s, m or l and an existing file")
        levels[size] = Path(path)
    for size, _ in args.env:
        if not levels[size].is_file():
            parser.error(f"no level for env {size}: {levels[size]} is missing (give --level {size}=FILE)")
    args.levels = levels
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from kinetix.devices import request_cpu_devices, use_present_platforms
    from kinetix.jaxcache import enable_compilation_cache

    use_present_platforms()  # before JAX starts, as the CLI does
    request_cpu_devices(args.devices)  # both sides share these devices
    enable_compilation_cache()
    with tempfile.TemporaryDirectory(prefix="kinetix-ab-") as tmp:
        sys.path.insert(0, str(export_tree(args.before, Path(tmp))))
        sides = Side(SUFFIX), Side("")
        for what, workloads in (("env", args.env), ("engine", args.engine)):
            for size, batch in workloads:
                level = args.levels[size] if what == "env" else None
                runs = [side.compiled(what, size, batch, args.steps, level) for side in sides]
                result = summary(what, size, batch, args.steps, *alternate(*runs, args.rounds))
                result["before"] = args.before
                if args.json:
                    print(json.dumps(result), flush=True)
                else:
                    print(f"{what} {size} {batch:>5}: before {result['before_steps_per_s']:>10,.0f}  after "
                          f"{result['after_steps_per_s']:>10,.0f} steps/s  after/before {result['ratio_median']:.3f} "
                          f"(rounds {result['ratio_min']:.3f}-{result['ratio_max']:.3f}, {result['rounds']}; "
                          f"fastest runs {result['ratio_best']:.3f})",
                          flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
