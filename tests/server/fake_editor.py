"""A minimal stand-in for server.editor.Editor (CONTRACT section 3) for session tests that need no real editing:
clicks add a small circle at the point, keys are recorded. Real editing is tested with the real Editor."""

from __future__ import annotations

import dataclasses

from kinetix.formats import BodySpec, LevelSpec, build, describe
from kinetix.level import LevelFile, empty_level, size_class


@dataclasses.dataclass
class FakeOverlay:
    preview: list = dataclasses.field(default_factory=list)
    selection: list = dataclasses.field(default_factory=list)
    guides: list = dataclasses.field(default_factory=list)
    snap_point: tuple | None = None
    message: str | None = None


class FakeEditor:
    def __init__(self, level=None, size="m"):
        self.size = size_class(size)
        if isinstance(level, LevelFile):
            self.spec = describe(level.level, level.params)
        else:
            self.spec = level or describe(empty_level(self.size))
        self.revision = 0
        self.tool = "select"
        self.clicks: list = []
        self.keys: list = []
        self.calls: list = []  # (method, args, kwargs) of pointer calls other than click
        self._cache = None

    def level_file(self) -> LevelFile:
        if self._cache is None or self._cache[0] != self.revision:
            self._cache = (self.revision, build(self.spec, self.size))
        return self._cache[1]

    def click(self, x, y, **mods):
        self.clicks.append((x, y))
        return None

    def key(self, key, **mods):
        self.keys.append((key, mods))
        return True

    def overlay(self):
        return FakeOverlay()

    def __getattr__(self, name):  # pointer_down / move / up, box_select, hover: recorded, no effect
        if name.startswith("_"):
            raise AttributeError(name)
        return lambda *args, **kwargs: self.calls.append((name, args, kwargs))


def falling_win_spec() -> LevelSpec:
    """A green ball above a fixed blue block: it falls and wins within about a second."""
    spec = describe(empty_level("m"))
    spec.bodies.append(BodySpec(path="ball", shape="circle", position=(2.5, 1.6), radius=0.25, role=1))
    half = [(-0.5, -0.2), (0.5, -0.2), (0.5, 0.2), (-0.5, 0.2)]
    spec.bodies.append(BodySpec(path="goal", shape="polygon", position=(2.5, 0.8), vertices=half, role=2, fixed=True))
    return spec
