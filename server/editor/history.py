"""Undo/redo as a bounded history of level snapshots.

Snapshots rather than commands: a `LevelSpec` of a Kinetix level is a few kilobytes, so copying
it per edit is cheap, and every edit (including imports and random levels) undoes the same way.
"""

from __future__ import annotations

import copy
import dataclasses

from kinetix.formats import LevelSpec
from kinetix.level import SizeClass


@dataclasses.dataclass
class Snapshot:
    spec: LevelSpec
    size: SizeClass


class History:
    def __init__(self, limit: int = 200):
        self.limit = limit
        self.undo_stack: list[Snapshot] = []
        self.redo_stack: list[Snapshot] = []

    def record(self, before: Snapshot) -> None:
        """Remember the state before an edit; a new edit drops everything that could be redone."""
        self.undo_stack.append(copy.deepcopy(before))
        del self.undo_stack[:-self.limit]
        self.redo_stack.clear()

    def undo(self, current: Snapshot) -> Snapshot | None:
        if not self.undo_stack:
            return None
        self.redo_stack.append(copy.deepcopy(current))
        return self.undo_stack.pop()

    def redo(self, current: Snapshot) -> Snapshot | None:
        if not self.redo_stack:
            return None
        self.undo_stack.append(copy.deepcopy(current))
        return self.redo_stack.pop()
