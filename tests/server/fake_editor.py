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

    def __getattr__(self, name):  # pointer_down / move / up, box_select, hover: recorded as no-ops
        if name.startswith("_"):
            raise AttributeError(name)
        return lambda *args, **kwargs: None


def spec_with_circle(x=2.5, y=3.0, r=0.3) -> LevelSpec:
    spec = describe(empty_level("m"))
    spec.bodies.append(BodySpec(path="bodies[new]", shape="circle", position=(x, y), radius=r))
    return spec
