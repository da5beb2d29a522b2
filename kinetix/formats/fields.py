"""Reading a parsed JSON level document with field paths: every error names where it is
("bodies[3].radius: expected a number, got string"), and numbers are checked and rounded to float32 as the level
arrays hold them. Used by the format readers (kinetix.formats.ours, kinetix.formats.kinetix_json)."""

from __future__ import annotations

import math

import numpy as np

from kinetix.level import (
    LevelError,
)

# A polygon whose vertex centroid is further than this (relative to its size) from the body
# position is recentred on load. Below it the offset is float32 round-off of an already centred
# polygon, and leaving it alone is what makes load -> save -> load bitwise stable.
MISSING = object()


def type_name(value) -> str:
    if value is None:
        return "null"
    return {bool: "boolean", int: "number", float: "number", str: "string", list: "list", dict: "object"}.get(
        type(value), type(value).__name__)


def index_keyed_list(value):
    """A dict keyed "0".."n-1" as the list of its values (other values unchanged)."""
    if isinstance(value, dict) and value and all(isinstance(k, str) for k in value):
        keys = set(value)
        if keys == {str(i) for i in range(len(value))}:
            return [value[str(i)] for i in range(len(value))]
    return value


class Fields:
    """One JSON object being read: every error names the field path, and unread keys can be listed."""

    def __init__(self, data, path: str, lists_may_be_dicts: bool = False):
        if not isinstance(data, dict):
            raise LevelError(f"{path or 'file'}: expected an object, got {type_name(data)}")
        self.data = data
        self.path = path
        self.read: set[str] = set()
        self.lists_may_be_dicts = lists_may_be_dicts  # the public Kinetix files key arrays by "0", "1", ...

    def where(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def require(self, *keys: str) -> None:
        missing = [k for k in keys if k not in self.data]
        if missing:
            names = ", ".join(missing)
            raise LevelError(f"{self.path or 'file'}: missing required field{'s' * (len(missing) > 1)} {names}")

    def unknown(self, allowed: set[str] | None = None) -> list[str]:
        return sorted(set(self.data) - (allowed if allowed is not None else self.read))

    def get(self, key: str, default=MISSING):
        self.read.add(key)
        if key not in self.data:
            if default is MISSING:
                raise LevelError(f"{self.path or 'file'}: missing required field {key}")
            return default
        return self.data[key]

    def number(self, key: str, default=MISSING, low: float | None = None, high: float | None = None,
               positive: bool = False) -> float:
        value = self.get(key, default)
        return check_number(value, self.where(key), low, high, positive)

    def integer(self, key: str, default=MISSING, low: int | None = None, high: int | None = None) -> int:
        value = self.get(key, default)
        where = self.where(key)
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            raise LevelError(f"{where}: expected an integer, got {value!r}")
        if (low is not None and value < low) or (high is not None and value > high):
            raise LevelError(f"{where}: {value} is out of range [{low}, {high}]")
        return value

    def boolean(self, key: str, default=MISSING) -> bool:
        value = self.get(key, default)
        if not isinstance(value, bool):
            raise LevelError(f"{self.where(key)}: expected true or false, got {value!r}")
        return value

    def string(self, key: str, default=MISSING) -> str:
        value = self.get(key, default)
        if not isinstance(value, str):
            raise LevelError(f"{self.where(key)}: expected a string, got {type_name(value)}")
        return value

    def vector(self, key: str, default=MISSING) -> tuple[float, float]:
        return check_vector(self.list_value(self.get(key, default), self.where(key)), self.where(key))

    def list(self, key: str, default=MISSING) -> list:
        return self.list_value(self.get(key, default), self.where(key))

    def list_value(self, value, where: str) -> list:
        if self.lists_may_be_dicts:
            value = index_keyed_list(value)
        if not isinstance(value, list):
            raise LevelError(f"{where}: expected a list, got {type_name(value)}")
        return value

    def child(self, key: str, default=MISSING) -> Fields:
        return Fields(self.get(key, default), self.where(key), self.lists_may_be_dicts)


def check_number(value, where: str, low: float | None = None, high: float | None = None,
                 positive: bool = False) -> float:
    """A finite number (optional bounds for values that are not level fields; those are in kinetix.ranges)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise LevelError(f"{where}: expected a number, got {value!r}")
    x = float(value)
    if not math.isfinite(x):
        raise LevelError(f"{where}: must be finite, got {x}")
    if positive and x <= 0:
        raise LevelError(f"{where}: must be > 0, got {x}")
    if (low is not None and x < low) or (high is not None and x > high):
        bounds = f">= {low}" if high is None else f"<= {high}" if low is None else f"in [{low}, {high}]"
        raise LevelError(f"{where}: must be {bounds}, got {x}")
    return x


def check_vector(value, where: str) -> tuple[float, float]:
    if not isinstance(value, list) or len(value) != 2:
        raise LevelError(f"{where}: expected [x, y], got {value!r}")
    return check_number(value[0], f"{where}[0]"), check_number(value[1], f"{where}[1]")


def f32(x) -> float:
    """The float32 value of x as the Python float with the shortest decimal form that reads back to it."""
    x32 = np.float32(x)
    short = float(str(x32))
    return short if np.float32(short) == x32 or not np.isfinite(x32) else float(x32)
