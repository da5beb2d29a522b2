"""A tab's editing side: the editor model a session edits (server.editor's, or a play-only stand-in), and the pointer
input (clicks, shift-box select, drags on viser's canvas) turned into editor calls in world coordinates."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any, Protocol


class EditTarget(Protocol):
    """What pointer input needs of a tab (a Session is one): its viser client, the screen-to-world mapping, the
    editor calls and a redraw."""

    client: Any

    def world(self, screen_pos) -> tuple[float, float]: ...

    def edit_call(self, method: str, *args, **kwargs) -> None: ...

    def refresh(self, force: bool = False) -> None: ...

log = logging.getLogger(__name__)


def default_editor_factory() -> Callable:
    """server.editor.Editor (CONTRACT section 3); without that package, a play-only stand-in so serving still works."""
    try:
        from server.editor import Editor
    except ImportError:
        log.warning("server.editor is not installed: levels can be played but not edited")
        return PlayOnlyEditor
    return Editor


class PlayOnlyEditor:
    """The part of the Editor interface a session needs to show and play a level, with every edit refused."""

    tool = "none"
    selection: list = []

    def __init__(self, level=None, size: str = "m"):
        from kinetix.formats import describe
        from kinetix.level import LevelFile, empty_level, size_class

        if level is None:
            level = LevelFile(empty_level(size_class(size)))
        self._level_file = level if isinstance(level, LevelFile) else None
        if self._level_file is None:
            from kinetix.formats import build

            self._level_file = build(level, size_class(size))
        self.spec = describe(self._level_file.level, self._level_file.params)
        self.size = self._level_file.size
        self.revision = 0

    def level_file(self):
        return self._level_file

    def overlay(self):
        return None

    def key(self, key: str, **mods) -> bool:
        return False

    def __getattr__(self, name: str):  # pointer_down, click, box_select, ...: no editing without the editor
        if name.startswith("_"):
            raise AttributeError(name)
        return lambda *args, **kwargs: "editing needs the server.editor package"


class PointerInput:
    """Wires a session's viser scene events to its editor (Session.edit_call), in the arrival order."""

    def __init__(self, session: EditTarget):
        self.session = session
        self._wire()

    def _wire(self) -> None:
        # viser runs plain callbacks on a thread pool fire-and-forget, so a drag's start and update could run out
        # of order; async callbacks run in arrival order on viser's event loop. They only do quick editor calls
        # and an edit-mode render (a few ms).
        async def on_click(event) -> None:
            self._on_click(event)

        async def on_rect_select(event) -> None:
            self._on_rect_select(event)

        async def on_drag(event) -> None:
            self._on_drag(event)

        scene = self.session.client.scene
        scene.on_click()(on_click)
        scene.on_rect_select(modifier="shift")(on_rect_select)
        # An invisible sphere around the camera catches drags anywhere on the canvas (study section 2).
        self._catcher = scene.add_icosphere("/kinetix/catcher", radius=200.0, color=(255, 255, 255), opacity=0.0,
                                            side="double")
        self._catcher.on_drag("left")(on_drag)
        self.session.client.camera.on_update(lambda _: self.session.refresh())

    def _on_click(self, event) -> None:
        pos = event.screen_pos
        x, y = self.session.world(pos[0] if isinstance(pos[0], list | tuple) else pos)
        self.session.edit_call("click", x, y)

    def _on_rect_select(self, event) -> None:
        x0, y0 = self.session.world(event.screen_min)
        x1, y1 = self.session.world(event.screen_max)
        self.session.edit_call("box_select", min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1), add=False)

    def _on_drag(self, event) -> None:
        mods = {"shift": event.modifier in ("shift", "shift+ctrl"), "ctrl": event.modifier in ("ctrl", "cmd/ctrl")}
        if event.phase == "start":
            self.session.edit_call("pointer_down", *self.session.world(event.start_screen_pos), **mods)
            self.session.edit_call("pointer_move", *self.session.world(event.end_screen_pos), **mods)
        elif event.phase == "update":
            self.session.edit_call("pointer_move", *self.session.world(event.end_screen_pos), **mods)
        else:
            self.session.edit_call("pointer_up", *self.session.world(event.end_screen_pos), **mods)
