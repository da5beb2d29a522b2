"""The command line that the per-episode diagnostics of a trained agent share (kinetix.agents.binding_entropy,
kinetix.agents.health): AGENT [--level levels ...] [--steps 64] [--seed 0] [--json]."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable

from kinetix.agents.checkpoint import CheckpointError
from kinetix.cli import positive_int
from kinetix.level import LevelError, LevelFile
from kinetix.level_source import eval_levels

Measure = Callable[..., dict]  # measure(agent, levels, steps=..., seed=...) -> a JSON-able result


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
