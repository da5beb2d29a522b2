"""Levels in and out of the editor: file bytes in either format, exports, new, random and mutated levels.

Every function returns a fresh, normalised `LevelSpec` (the one `describe` gives of the built level:
polygons first, float32 values), so body indices in the editor always match the built arrays.
Random and mutated levels run JAX programs; each is compiled once per size class per process.
"""

from __future__ import annotations

import functools
import json

import jax

import jax2d
from kinetix.formats import LevelSpec, build, describe, kinetix_json, ours, smallest_size
from kinetix.level import LevelError, LevelFile, SizeClass, empty_level, size_class
from kinetix.levels import detect_format, dumps


class EditorError(ValueError):
    """An editor request that cannot be done; the message is meant for the user."""


def normalised(file: LevelFile) -> LevelSpec:
    spec = describe(file.level, file.params, file.name)
    spec.size = file.size
    return spec


def parse(data: bytes, filename: str = "") -> tuple[LevelSpec, SizeClass]:
    """The level in `data` (our format or the public Kinetix JSON); EditorError says what is wrong."""
    where = filename or "upload"
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise EditorError(f"{where} is not UTF-8 text: {error.reason} at byte {error.start}") from None
    try:
        document = json.loads(text)
    except json.JSONDecodeError as error:
        raise EditorError(f"{where} is not valid JSON: {error.msg} at line {error.lineno} column {error.colno}"
                          ) from None
    except RecursionError:
        raise EditorError(f"{where} is nested too deeply to be a level") from None
    try:
        fmt = detect_format(document)
        spec = ours.read(document) if fmt == "ours" else kinetix_json.read(document)
        if not spec.name and filename:
            spec.name = filename.rsplit("/", 1)[-1].split(".")[0]
        file = build(spec)
    except LevelError as error:
        raise EditorError(f"{where}: {error}") from None
    except (ValueError, TypeError, KeyError, IndexError, AttributeError, OverflowError) as error:
        raise EditorError(f"{where}: invalid level ({type(error).__name__}: {error})") from None
    return normalised(file), file.size


def export(file: LevelFile, format: str) -> str:
    return export_with_notes(file, format)[0]


def export_notes(file: LevelFile, format: str) -> list[str]:
    """What the export does and what the format's other tools do differently with the file, in sentences: for
    the Kinetix format first what was split and the size class written; [] for our format."""
    return export_with_notes(file, format)[1]


def export_with_notes(file: LevelFile, format: str) -> tuple[str, list[str]]:
    """(file text, export_notes) from one export: a Kinetix export splits polygons and picks the size."""
    if format not in ("ours", "kinetix"):
        raise EditorError(f"unknown format {format!r}: use ours or kinetix")
    try:
        if format == "ours":
            return dumps(file, format), []
        export = kinetix_json.prepare(file)
        return export.text(), [export.summary(), *export.notes()]
    except LevelError as error:
        raise EditorError(str(error)) from None


def new_level(size: str | SizeClass) -> LevelSpec:
    size = size_class(size)
    return normalised(LevelFile(empty_level(size), size=size))


@functools.cache
def _sampler(size: SizeClass):
    from kinetix.generate import sample_level
    return jax2d.jit(lambda key: sample_level(key, size))


@functools.cache
def _mutator(n: int):
    from kinetix.mutate import mutate
    return jax2d.jit(lambda key, level: mutate(key, level, n))


def warm_up(size: str | SizeClass = "m") -> None:
    """Compile the random-level and shake-it-up programs of this size class now (tens of seconds without the
    persistent compile cache), e.g. on a background thread at server start, so the first button press is quick."""
    size = size_class(size)
    level = _sampler(size)(jax.random.PRNGKey(0))
    jax.block_until_ready(_mutator(3)(jax.random.PRNGKey(0), level))


def random_level(seed: int, size: str | SizeClass) -> LevelSpec:
    size = size_class(size)
    level = _sampler(size)(jax.random.PRNGKey(seed))
    return normalised(LevelFile(jax.device_get(level), size=size))


def shaken(file: LevelFile, seed: int, n: int = 3) -> LevelSpec:
    """The level after `n` random mutators (kinetix.mutate), seeded; edits that would break it are skipped."""
    level = _mutator(n)(jax.random.PRNGKey(seed), file.level)
    out = LevelFile(jax.device_get(level), file.params, file.size, file.name)
    return normalised(out)


def fits(spec: LevelSpec, size: SizeClass) -> LevelFile:
    """build(spec, size) with an EditorError naming what is wrong."""
    try:
        return build(spec, size)
    except LevelError as error:
        raise EditorError(str(error)) from None


__all__ = ["EditorError", "parse", "export", "export_notes", "export_with_notes", "new_level", "random_level",
           "shaken", "fits", "smallest_size", "warm_up"]
