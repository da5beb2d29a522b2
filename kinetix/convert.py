"""`kinetix convert IN OUT [--to ours|kinetix] [--size s|m|l]`: rewrite a level file in the other format.

The output is written to a temporary file and renamed into place, so on any error OUT is left as it was.
"""

from __future__ import annotations

import argparse
import sys

from kinetix.formats import describe, kinetix_json
from kinetix.level import LevelError
from kinetix.levels import load_level, resize, save_level


def convert(source: str, target: str, to: str | None = None, size: str | None = None) -> str:
    """Convert `source` into `target`; returns the format written (default: the other one than the input's)."""
    file = load_level(source)
    if size is not None:
        file = resize(file, size)
    fmt = to or ("kinetix" if file.format == "ours" else "ours")
    save_level(file, target, format=fmt)
    for warning in file.warnings:
        print(f"{source}: warning: {warning}", file=sys.stderr)
    if fmt == "kinetix":  # what the public Kinetix will do differently with the file
        for note in kinetix_json.export_notes(describe(file.level, file.params, file.name)):
            print(f"{target}: note: {note}", file=sys.stderr)
    return fmt


def run(args: argparse.Namespace) -> int:
    try:
        fmt = convert(args.input, args.output, args.to, args.size)
    except LevelError as error:
        print(f"kinetix convert: {error}", file=sys.stderr)
        return 1
    print(f"wrote {args.output} ({fmt} format)")
    return 0
