"""A run's zero-shot learning curve: the solve rate of its checkpoints on a level set against env steps.

    python -m kinetix.agents.eval_curve RUN [--level levels] [--attempts 100] [--seed 0]
    python -m kinetix.agents.eval_curve RUN --checkpoint DIR --results EVAL.jsonl

The first form evaluates RUN/checkpoint (`kinetix eval`'s protocol: sampled actions, `attempts` episodes per
level); the second records an evaluation already made (`kinetix eval --json` output) of another checkpoint of
the run, e.g. one restored from git. Either way the point goes at the checkpoint's env steps (its
config.json's info.steps) into RUN/levels-curve.json, replacing a point of the same steps and protocol, and
RUN/levels-curve.png is redrawn. A long run picks its checkpoints on this curve, never on the shared sets
(issue 33), so the curve is kept beside the run's training curve (curve.png, on the levels it trained on).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from kinetix.agents.checkpoint import CheckpointError
from kinetix.agents.plot import learning_curve
from kinetix.cli import positive_int
from kinetix.level import LevelError

CURVE_JSON = "levels-curve.json"
CURVE_PNG = "levels-curve.png"


class CurveError(ValueError):
    """A checkpoint without its step count, or evaluation results that cannot be read."""


def checkpoint_steps(checkpoint: Path) -> int:
    """Env steps a checkpoint was trained for (its config.json's info.steps)."""
    try:
        info = json.loads((checkpoint / "config.json").read_text())["info"]
        return int(info["steps"])
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise CurveError(f"{checkpoint}: no info.steps in config.json ({error})") from error


def read_results(path: Path) -> list[dict]:
    """`kinetix eval --json` output: one {"level", "solve_rate", "mean_return"} per line."""
    try:
        rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
        for row in rows:
            float(row["solve_rate"]), float(row["mean_return"]), str(row["level"])
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise CurveError(f"{path}: not `kinetix eval --json` output ({error})") from error
    if not rows:
        raise CurveError(f"{path}: no results")
    return rows


def point(env_steps: int, results: list[dict], level_set: str, attempts: int, seed: int) -> dict:
    """One curve point: the mean solve rate and return over the levels, and each level's solve rate."""
    return {
        "env_steps": env_steps,
        "solve_rate": sum(r["solve_rate"] for r in results) / len(results),
        "mean_return": sum(r["mean_return"] for r in results) / len(results),
        "level_set": level_set, "attempts": attempts, "seed": seed,
        "levels": {Path(r["level"]).stem: r["solve_rate"] for r in results},
    }


def add_point(run: Path, new: dict) -> list[dict]:
    """Merge `new` into RUN/levels-curve.json (same steps and protocol: replaced), sorted by steps; redraw
    RUN/levels-curve.png, one line per level set and protocol. Both files are replaced whole."""
    path = run / CURVE_JSON
    points = json.loads(path.read_text()) if path.exists() else []
    protocol = lambda p: (p["level_set"], p["attempts"], p["seed"])  # noqa: E731
    points = [p for p in points if (p["env_steps"], protocol(p)) != (new["env_steps"], protocol(new))]
    points = sorted(points + [new], key=lambda p: (protocol(p), p["env_steps"]))
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(points, indent=1) + "\n")
    os.replace(tmp, path)
    lines: dict[str, list[dict]] = {}
    for p in points:
        lines.setdefault(f"{p['level_set']}, {p['attempts']} attempts, seed {p['seed']}", []).append(p)
    learning_curve(run / CURVE_PNG, lines, titles=("mean episode return, zero-shot",
                                                  "mean solve rate over the levels, zero-shot"))
    return points


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m kinetix.agents.eval_curve", description=__doc__.split("\n")[0])
    parser.add_argument("run", type=Path, help="the run's directory (kinetix train --out)")
    parser.add_argument("--checkpoint", type=Path, help="the checkpoint evaluated (default: RUN/checkpoint)")
    parser.add_argument("--results", type=Path, help="its `kinetix eval --json` output, instead of evaluating here")
    parser.add_argument("--level", default="levels",
                        help="the level set: a directory, a file or generated-s|m|l|all (default: levels)")
    parser.add_argument("--attempts", type=positive_int, default=100, help="episodes per level (default: 100)")
    parser.add_argument("--seed", type=int, default=0, help="evaluation seed (default: 0)")
    args = parser.parse_args(argv)
    checkpoint = args.checkpoint or args.run / "checkpoint"
    try:
        steps = checkpoint_steps(checkpoint)
        if args.results:
            results = read_results(args.results)
        else:
            from kinetix.agents.evaluate import evaluate
            from kinetix.level_source import eval_levels

            levels = eval_levels(args.level)
            results = evaluate(str(checkpoint), levels, attempts=args.attempts, seed=args.seed)
    except (CurveError, LevelError, CheckpointError) as error:
        print(f"eval_curve: {error}", file=sys.stderr)
        return 2
    new = point(steps, results, args.level, args.attempts, args.seed)
    points = add_point(args.run, new)
    print(f"{args.run / CURVE_JSON}: {steps:,} env steps -> solve rate {new['solve_rate']:.3f} on {args.level} "
          f"({len(points)} points)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
