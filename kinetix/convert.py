"""`kinetix convert IN OUT [--to ours|kinetix] [--size s|m|l]`: rewrite a level file in the other format.

The output is written to a temporary file and renamed into place, so on any error OUT is left as it was.
"""

from __future__ import annotations

import argparse
import sys

from kinetix.formats import kinetix_json
from kinetix.level import LevelError
from kinetix.levels import load_level, save_level, write_atomically


def convert(source: str, target: str, to: str | None = None, size: str | None = None) -> tuple[str, str]:
    """Convert `source` into `target`; returns (the format written, default: the other one than the input's, and
    what a Kinetix export did: "split 1 polygon (6 vertices) into 2 parts welded by 1 fixed joint; exported as
    size l"; "" for our format)."""
    file = load_level(source)
    fmt = to or ("kinetix" if file.format == "ours" else "ours")
    for warning in file.warnings:
        print(f"{source}: warning: {warning}", file=sys.stderr)
    if fmt != "kinetix":
        save_level(file, target, format=fmt, size=size)
        return fmt, ""
    export = kinetix_json.prepare(file, size)
    write_atomically(target, export.text())
    for note in export.notes():  # what the public Kinetix will do differently with the file
        print(f"{target}: note: {note}", file=sys.stderr)
    return fmt, export.summary()


def run(args: argparse.Namespace) -> int:
    try:
        fmt, summary = convert(args.input, args.output, args.to, args.size)
    except LevelError as error:
        print(f"kinetix convert: {error}", file=sys.stderr)
        return 1
    print(f"wrote {args.output} ({fmt} format{': ' + summary if summary else ''})")
    return 0
