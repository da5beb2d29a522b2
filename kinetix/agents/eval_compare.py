"""Compare `kinetix eval --json` results of checkpoints: mean solve rate per level set, and churn between them.

    python -m kinetix.agents.eval_compare A.jsonl B.jsonl [C.jsonl ...] [--json]

Each file is one checkpoint's evaluation (one {"level", "solve_rate", "mean_return"} per line; several sets may
be concatenated in one file). Levels are grouped by their set: the part of the level's name before its last "/"
("levels", "generated-s", "../shared/kinetix-levels/m"). For every file the mean solve rate of each set is
printed, and for each file after the first its churn against the one before it, per set: the mean over the
levels both evaluated of |change in solve rate|.

Why churn: along the general agent's runs the mean solve rate of one checkpoint and the next often differed by
little while single levels swung from solved to unsolved and back (kinetix/agents/general/README.md, the buffer
and step-size A/Bs). A mean hides that trade; churn shows how much of what the policy could do it gave up or
gained between checkpoints, so a setting that keeps what it learns can be told from one that only moves.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from kinetix.agents.eval_curve import CurveError, read_results


def level_set(level: str) -> str:
    """The set a level belongs to: its name up to the last "/" ("" for a bare name)."""
    return level.rpartition("/")[0]


def by_set(rows: list[dict]) -> dict[str, dict[str, float]]:
    """{set: {level: solve_rate}}, in the order the sets first appear. A level twice in one file is an error:
    which of its two results to compare would be a guess."""
    sets: dict[str, dict[str, float]] = {}
    for row in rows:
        levels = sets.setdefault(level_set(row["level"]), {})
        if row["level"] in levels:
            raise CurveError(f"{row['level']} appears twice in one evaluation")
        levels[row["level"]] = float(row["solve_rate"])
    return sets


def churn(before: dict[str, float], after: dict[str, float]) -> tuple[float, int] | None:
    """(mean |after - before| over the levels in both, their count), or None when they share no level."""
    common = sorted(set(before) & set(after))
    if not common:
        return None
    return sum(abs(after[k] - before[k]) for k in common) / len(common), len(common)


def compare(paths: list[Path]) -> list[dict]:
    """One entry per file: {"file", "sets": {set: {"levels", "mean"}}, "churn": {set: {"levels", "churn"}}},
    churn against the previous file (empty for the first)."""
    evaluations = [by_set(read_results(path)) for path in paths]
    out = []
    for i, (path, sets) in enumerate(zip(paths, evaluations, strict=True)):
        entry = {"file": str(path),
                 "sets": {name: {"levels": len(levels), "mean": sum(levels.values()) / len(levels)}
                          for name, levels in sets.items()},
                 "churn": {}}
        if i:
            for name, levels in sets.items():
                moved = churn(evaluations[i - 1].get(name, {}), levels)
                if moved is not None:
                    entry["churn"][name] = {"levels": moved[1], "churn": moved[0]}
        out.append(entry)
    return out


def render(entries: list[dict]) -> str:
    lines = []
    for entry in entries:
        lines.append(entry["file"])
        for name, summary in entry["sets"].items():
            moved = entry["churn"].get(name)
            since = (f"   churn {moved['churn']:.3f} over {moved['levels']} levels against the file before"
                     if moved else "")
            lines.append(f"  {name or '(no set)'}: {summary['levels']} levels, mean solve rate {summary['mean']:.3f}"
                         f"{since}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m kinetix.agents.eval_compare",
                                     description="mean solve rate per level set of `kinetix eval --json` results, "
                                                 "and churn between consecutive files")
    parser.add_argument("results", nargs="+", type=Path, metavar="EVAL.jsonl",
                        help="`kinetix eval --json` output, one file per checkpoint, oldest first")
    parser.add_argument("--json", action="store_true", help="print the comparison as JSON")
    args = parser.parse_args(argv)
    try:
        entries = compare(args.results)
    except CurveError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(json.dumps(entries, indent=1) if args.json else render(entries))
    return 0


if __name__ == "__main__":
    sys.exit(main())
