"""Loading and saving level files in either format, detected from the content.

    file = load_level("levels/car.json", size="l")   # -> LevelFile(level, params, size, ...)
    save_level(file, "car.kinetix.json", format="kinetix")

Every problem with a file (unreadable, not JSON, wrong fields, bad geometry, too big for the
size class) raises LevelError with a message naming the field; nothing else escapes.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

from kinetix.formats import build, describe, kinetix_json, ours
from kinetix.level import Level, LevelError, LevelFile, LevelParams, SizeClass, size_class

FORMATS = ("ours", "kinetix")


def detect_format(data) -> str:
    """"ours" or "kinetix" from a parsed document's top-level keys."""
    if isinstance(data, dict):
        if "format_version" in data:
            return "ours"
        if "env_state" in data:
            return "kinetix"
    found = f"keys {sorted(data)[:8]}" if isinstance(data, dict) else type(data).__name__
    raise LevelError(f"not a level file: expected format_version (our format) or env_state (Kinetix), found {found}")


def read_json(path: str | os.PathLike) -> object:
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise LevelError(f"cannot read {path}: {error}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as error:
        raise LevelError(f"{path} is not valid JSON: {error.msg} at line {error.lineno} column {error.colno}") from None
    except RecursionError:
        raise LevelError(f"{path} is nested too deeply to be a level") from None


def load_level(source: str | os.PathLike | dict, size: str | SizeClass | None = None) -> LevelFile:
    """A level from a file path or a parsed document, in its own size class or in `size`.

    A level loads into any size class it fits (smaller levels are padded with inactive slots);
    a level too big for `size` raises LevelError listing every overflow.
    """
    if not isinstance(source, (dict, str, os.PathLike)):
        raise LevelError(f"expected a file path or a parsed level document, got {type(source).__name__}")
    data = source if isinstance(source, dict) else read_json(source)
    fmt = detect_format(data)
    try:
        spec = ours.read(data) if fmt == "ours" else kinetix_json.read(data)
        if not spec.name and not isinstance(source, dict):
            spec.name = Path(source).stem
        file = build(spec, size_class(size) if size is not None else None)
    except LevelError:
        raise
    except (ValueError, TypeError, KeyError, IndexError, AttributeError, OverflowError) as error:
        # A reader bug or an input we did not foresee: still a LevelError, with what went wrong.
        raise LevelError(f"invalid level ({type(error).__name__}: {error})") from error
    return LevelFile(file.level, file.params, file.size, file.name, fmt, file.warnings)


def as_level_file(level: Level | LevelFile) -> LevelFile:
    if isinstance(level, LevelFile):
        return level
    if isinstance(level, Level):
        return LevelFile(level, LevelParams())
    raise LevelError(f"expected a Level or LevelFile, got {type(level).__name__}")


def resize(level: Level | LevelFile, size: str | SizeClass) -> LevelFile:
    """The same level in another size class (only active entities are kept; indices are fixed)."""
    file = as_level_file(level)
    spec = describe(file.level, file.params, file.name)
    out = build(spec, size_class(size))
    warnings = tuple(dict.fromkeys(file.warnings + out.warnings))
    return LevelFile(out.level, out.params, out.size, out.name, file.format, warnings)


def to_document(level: Level | LevelFile, format: str = "ours", size: str | SizeClass | None = None) -> dict:
    """The level as a JSON-ready document, optionally in another size class. The Kinetix format splits polygons
    of more than 4 vertices and picks a size class that holds the result (kinetix_json.prepare); a `size` given
    must hold it."""
    file = as_level_file(level)
    if format == "ours":
        return ours.write(file if size is None else resize(file, size))
    if format == "kinetix":
        return kinetix_json.write(file, size)
    raise LevelError(f"unknown format {format!r}: use one of {', '.join(FORMATS)}")


def dumps(level: Level | LevelFile, format: str = "ours", size: str | SizeClass | None = None) -> str:
    """The level as file text (see to_document)."""
    file = as_level_file(level)
    if format == "ours":
        return ours.dumps(file if size is None else resize(file, size))
    if format == "kinetix":
        return kinetix_json.prepare(file, size).text()
    raise LevelError(f"unknown format {format!r}: use one of {', '.join(FORMATS)}")


def save_level(level: Level | LevelFile, path: str | os.PathLike, format: str = "ours",
               size: str | SizeClass | None = None) -> None:
    """Write the level to `path` atomically (a temporary file renamed into place), optionally resized."""
    write_atomically(path, dumps(level, format, size))


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_atomically(path: str | os.PathLike, text: str) -> None:
    path = Path(path)
    try:
        handle, temporary = tempfile.mkstemp(dir=path.parent or ".", prefix=f".{path.name}.", suffix=".tmp")
    except OSError as error:
        raise LevelError(f"cannot write {path}: {error}") from None
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as out:
            out.write(text)
        os.chmod(temporary, 0o666 & ~_umask())  # mkstemp makes the file private; give it the usual mode
        os.replace(temporary, path)
    except BaseException as error:
        Path(temporary).unlink(missing_ok=True)
        if isinstance(error, OSError):
            raise LevelError(f"cannot write {path}: {error}") from None
        raise
