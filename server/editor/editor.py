"""The editor's document: the level being edited, its history, the tool in use, the selection and the overlay.

Every edit builds a candidate `LevelSpec`, checks it with `kinetix.formats.build` in the current size
class, and only then replaces the level and records one undo step; a refused edit changes nothing
and leaves a message. The 4 standard walls are part of the level but not of the editing: they
cannot be selected, moved or deleted (they can be the other end of a joint, e.g. to pin a body).
The pointer's gestures and the drawing tools are in server.editor.gestures (PointerGestures, inherited).
Not thread-safe on its own: the server session calls it under its lock.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable

from kinetix.formats import LevelSpec, build
from kinetix.level import SIZES, LevelError, LevelFile, SizeClass, size_class
from kinetix.ranges import RANGES
from server.editor import levelio, properties
from server.editor import selection as sel
from server.editor.geometry import Point, outline, rotate
from server.editor.gestures import SNAP_RADIUS, PointerGestures
from server.editor.history import History, Snapshot
from server.editor.levelio import EditorError

TOOLS = ("select", "circle", "rectangle", "triangle", "polygon", "revolute", "fixed", "thruster")
PASTE_OFFSET = (0.25, -0.25)
CAPACITY_NAMES = {"polygons": "polygon", "circles": "circle", "joints": "joint", "thrusters": "thruster"}
GROWTH = {"s": "m", "m": "l", "l": "xl"}  # the next larger size class a full level is offered (none after xl or custom)


@dataclasses.dataclass
class Overlay:
    """What the renderer draws on top of the level, all in world coordinates."""

    preview: list[dict] = dataclasses.field(default_factory=list)
    selection: list[dict] = dataclasses.field(default_factory=list)
    guides: list[tuple[float, float, float, float]] = dataclasses.field(default_factory=list)
    snap_point: tuple[float, float] | None = None
    message: str | None = None


class Editor(PointerGestures):
    def __init__(self, level: LevelFile | LevelSpec | None = None, size: str = "m"):
        if level is None:
            self.size = size_class(size)
            spec = levelio.new_level(self.size)
        elif isinstance(level, LevelFile):
            self.size = level.size
            spec = levelio.normalised(level)
        elif isinstance(level, LevelSpec):
            self.size = level.size or size_class(size)
            spec = levelio.normalised(levelio.fits(level, self.size))
        else:
            raise EditorError(f"expected a LevelFile, LevelSpec or None, got {type(level).__name__}")
        self.spec: LevelSpec = spec
        self._file: LevelFile = build(spec, self.size)
        self._file_revision = 0
        self.revision = 0
        self.history = History()
        # The level the editor started with. While it is still shown, unchanged (the very same object: every edit,
        # undo or restored draft replaces self.spec), a level opened over it (a gallery link, an upload) becomes the
        # history's base, so undo never goes back to that blank or default level.
        self._start_spec = spec
        self.tool = "select"
        self.selection: list[tuple[str, int]] = []
        self.snapping = True
        self.grid = 0.1
        self.snap_radius = SNAP_RADIUS  # m (gestures.SNAP_RADIUS); the session sets it from its canvas
        self.message: str | None = None
        # After a "no polygon left" refusal: the size class the panel offers to move the level to, and the refused
        # edit, which grow_size() does again once the level has room.
        self.size_offer: str | None = None
        self._retry: Callable[[], str | None] | None = None
        self._points: list[Point] = []  # polygon vertices placed so far
        self._press: dict | None = None  # the pointer press in progress
        self._hover: Point | None = None
        self._guides: list = []
        self._snap_point: Point | None = None
        self._last_click: tuple[Point, list, int] | None = None
        self._clip: sel.Clip | None = None
        self._pastes = 0

    # ------------------------------------------------------------ state and committing

    def _bump(self) -> None:
        self.revision += 1

    def _say(self, message: str | None, offer: str | None = None,
             retry: Callable[[], str | None] | None = None) -> str | None:
        self.message = message
        self.size_offer, self._retry = offer, retry
        self._bump()
        return message

    def notify(self, message: str | None) -> str | None:
        """Show a message (or clear it with None) in the overlay; bumps the revision."""
        return self._say(message)

    def _snapshot(self) -> Snapshot:
        return Snapshot(self.spec, self.size)

    def _candidate(self) -> LevelSpec:
        return copy.deepcopy(self.spec)

    def _commit(self, candidate: LevelSpec, size: SizeClass | None = None, selection=None,
                before: Snapshot | None = None) -> str | None:
        """Replace the level by `candidate` if it builds in `size`; one undo step. Returns the refusal or None."""
        size = size or self.size
        sel.renumber(candidate)
        try:
            file = build(candidate, size)
        except LevelError as error:
            return self._say(str(error))
        self.history.record(before or self._snapshot())
        self.spec, self.size, self._file, self._file_revision = candidate, size, file, self.revision + 1
        if selection is not None:
            self.selection = selection
        self._clean_selection()
        self.message, self.size_offer, self._retry = None, None, None
        # The guides showed how the pointer snapped while it moved; the edit is made, so they go (they stayed until
        # the next pointer event). The ring at the feature it snapped to stays: it shows what the edit snapped to.
        self._guides = []
        self._bump()
        self._file_revision = self.revision
        return None

    def _clean_selection(self) -> None:
        counts = {"body": len(self.spec.bodies), "joint": len(self.spec.joints), "thruster": len(self.spec.thrusters)}
        walls = sel.wall_count(self.spec)
        self.selection = [(k, i) for k, i in dict.fromkeys(self.selection)
                          if 0 <= i < counts[k] and not (k == "body" and i < walls)]

    def level_file(self) -> LevelFile:
        """The level built in its size class (cached per revision); what the session plays."""
        if self._file_revision != self.revision:
            try:
                self._file = build(self.spec, self.size)
            except LevelError:
                pass  # a drag in progress can pass through a state that does not build; keep the last good one
            self._file_revision = self.revision
        return self._file

    def _room(self, kind: str, extra: int = 1, retry: Callable[[], str | None] | None = None) -> str | None:
        """Refuse (and say so) when `extra` more of `kind` ("polygons", ...) do not fit; None if they do.

        The refusal offers the next size class when there is one (size_offer; the panel shows a button), and keeps
        `retry`, the refused edit, for grow_size() to do once the level is there."""
        used = self.limits()[kind][0]
        capacity = getattr(self.size, kind)
        if used + extra <= capacity:
            return None
        refusal = f"no {CAPACITY_NAMES[kind]} left: {used} of {capacity} used in size {self.size.name}"
        bigger = GROWTH.get(self.size.name) if SIZES.get(self.size.name) == self.size else None
        if bigger is not None and used + extra <= getattr(SIZES[bigger], kind):
            return self._say(f"{refusal}; \"Move to size {bigger}\" in the panel makes room", bigger, retry)
        return self._say(refusal)

    def grow_size(self) -> str | None:
        """Move the level to the size class offered by the last "no ... left" refusal (one undo step), then do the
        refused edit again (another step). Returns the refusal, or None."""
        offer, retry = self.size_offer, self._retry
        if offer is None:
            return self._say("no larger size class is offered: the level fits, or it is already in size l")
        if refusal := self.set_size(offer):
            return refusal
        return retry() if retry is not None else None

    def limits(self) -> dict[str, tuple[int, int]]:
        """(used, capacity) per kind; polygons include the 4 walls, as the size classes do."""
        polygons = sum(b.shape == "polygon" for b in self.spec.bodies)
        return {"polygons": (polygons, self.size.polygons),
                "circles": (len(self.spec.bodies) - polygons, self.size.circles),
                "joints": (len(self.spec.joints), self.size.joints),
                "thrusters": (len(self.spec.thrusters), self.size.thrusters)}

    # ------------------------------------------------------------ undo

    @property
    def can_undo(self) -> bool:
        return bool(self.history.undo_stack)

    @property
    def can_redo(self) -> bool:
        return bool(self.history.redo_stack)

    def _restore(self, snapshot: Snapshot | None) -> bool:
        if snapshot is None:
            return False
        self.spec, self.size = snapshot.spec, snapshot.size
        self._cancel()
        self._clean_selection()
        self.message, self.size_offer, self._retry = None, None, None
        self._bump()
        return True

    def undo(self) -> bool:
        return self._restore(self.history.undo(self._snapshot()))

    def redo(self) -> bool:
        return self._restore(self.history.redo(self._snapshot()))

    def load_draft(self, spec: LevelSpec, size: SizeClass, undo: list[tuple[LevelSpec, SizeClass]],
                   redo: list[tuple[LevelSpec, SizeClass]]) -> None:
        """Become a saved draft (server.drafts.store): this level and these undo/redo stacks, oldest first.

        Only the current level is built (LevelError if it does not build): the undo steps were built when made."""
        file = build(spec, size)
        self._cancel()
        self.spec, self.size, self._file = spec, size, file
        self.history.undo_stack[:] = [Snapshot(s, z) for s, z in undo][-self.history.limit:]
        self.history.redo_stack[:] = [Snapshot(s, z) for s, z in redo]
        self.selection = []
        self.message = None
        self._bump()
        self._file_revision = self.revision

    # ------------------------------------------------------------ tools and pointer input

    def set_tool(self, name: str) -> None:
        if name not in TOOLS:
            raise EditorError(f"unknown tool {name!r}: use one of {', '.join(TOOLS)}")
        self._cancel()
        self.tool = name
        self.message, self.size_offer, self._retry = None, None, None
        self._bump()

    def _cancel(self) -> None:
        self._points, self._press, self._guides, self._snap_point = [], None, [], None

    def _moving(self) -> set[int]:
        return sel.assembly(self.spec, sel.selected_bodies(self.spec, self.selection))

    def delete_selection(self) -> str | None:
        if not self.selection:
            return self._say("nothing selected")
        spec = self._candidate()
        sel.delete(spec, self.selection)
        return self._commit(spec, selection=[])

    def copy(self) -> str | None:
        if not self.selection:
            return self._say("nothing selected")
        self._clip = sel.copy_items(self.spec, self.selection)
        self._pastes = 0
        self._bump()
        return None

    def paste(self) -> str | None:
        if not self._clip or not self._clip[0]:
            return self._say("nothing to paste: copy something first")
        bodies, joints, thrusters = self._clip
        for kind, extra in (("polygons", sum(b.shape == "polygon" for b in bodies)),
                            ("circles", sum(b.shape == "circle" for b in bodies)),
                            ("joints", len(joints)), ("thrusters", len(thrusters))):
            if extra and (refusal := self._room(kind, extra)):
                return refusal
        self._pastes += 1
        spec = self._candidate()
        items = sel.paste(spec, self._clip, PASTE_OFFSET[0] * self._pastes, PASTE_OFFSET[1] * self._pastes)
        return self._commit(spec, selection=items)

    def duplicate_selection(self) -> str | None:
        if not self.selection:
            return self._say("nothing selected")
        clip, pastes = self._clip, self._pastes
        self._clip, self._pastes = sel.copy_items(self.spec, self.selection), 0
        try:
            return self.paste()
        finally:
            self._clip, self._pastes = clip, pastes  # duplicating leaves the clipboard alone

    def rotate_selection(self, degrees: float) -> str | None:
        moving = self._moving()
        if not moving:
            return self._say("select a body to rotate")
        spec = self._candidate()
        sel.rotate_bodies(spec, moving, math.radians(degrees), sel.pivot(spec, moving))
        return self._commit(spec)

    def scale_selection(self, factor: float) -> str | None:
        moving = self._moving()
        if not moving:
            return self._say("select a body to resize")
        if not (isinstance(factor, (int, float)) and math.isfinite(factor) and factor > 0):
            return self._say(f"scale factor must be > 0, got {factor!r}")
        spec = self._candidate()
        sel.scale_bodies(spec, moving, factor, sel.pivot(spec, moving))
        return self._commit(spec)

    # ------------------------------------------------------------ properties and globals

    def properties(self) -> dict:
        bodies = [properties.body_fields(self.spec, i) for k, i in self.selection if k == "body"]
        joints = [properties.joint_fields(self.spec, i) for k, i in self.selection if k == "joint"]
        thrusters = [properties.thruster_fields(self.spec, i) for k, i in self.selection if k == "thruster"]
        return {"bodies": bodies, "joints": joints, "thrusters": thrusters, "gravity": tuple(self.spec.gravity),
                "size": self.size.name, "params": dataclasses.asdict(self.spec.params)}

    def set_properties(self, **values) -> str | None:
        spec = self._candidate()
        pick = lambda kind: [i for k, i in self.selection if k == kind]  # noqa: E731
        try:
            properties.apply(spec, pick("body"), pick("joint"), pick("thruster"), values)
        except ValueError as error:
            return self._say(str(error))
        if spec == self.spec:
            return None
        return self._commit(spec)

    def set_gravity(self, gx: float, gy: float) -> str | None:
        bounds = RANGES["gravity"]  # the level format's range, so an accepted value always saves and loads
        for v in (gx, gy):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not bounds.low <= v <= bounds.high:
                return self._say(f"gravity must be numbers in {bounds.text()}, got ({gx!r}, {gy!r})")
        spec = self._candidate()
        spec.gravity = (float(gx), float(gy))
        return None if spec == self.spec else self._commit(spec)

    def set_params(self, **values) -> str | None:
        """Change episode and physics settings (LevelParams fields); one undo step. Returns the refusal or None."""
        try:
            params = properties.checked_params(self.spec.params, values)
        except ValueError as error:
            return self._say(str(error))
        spec = self._candidate()
        spec.params = params
        return None if spec == self.spec else self._commit(spec)

    def set_size(self, size: str) -> str | None:
        try:
            new = size_class(size)
        except LevelError as error:
            return self._say(str(error))
        if new == self.size:
            return None
        spec = self._candidate()
        spec.size = new
        try:
            build(spec, new)
        except LevelError as error:
            return self._say(f"cannot change to size {new.name}: {error}")
        return self._commit(spec, new)

    # ------------------------------------------------------------ whole levels

    def new_level(self, size: str = "m") -> None:
        new = size_class(size)
        self._cancel()
        self._commit(levelio.new_level(new), new, selection=[])

    def shake_it_up(self, seed: int) -> str | None:
        spec = levelio.shaken(self.level_file(), seed)
        if spec == self.spec:
            return self._say("no mutation applied: nothing changed")
        return self._commit(spec, selection=[])

    def random_level(self, seed: int, size: str | None = None) -> str | None:
        new = size_class(size) if size is not None else self.size
        self._cancel()
        return self._commit(levelio.random_level(seed, new), new, selection=[])

    def import_bytes(self, data: bytes, filename: str = "") -> None:
        """Open a level file (either format). Over the untouched starting level it is the history's base (undo
        does not go back to the blank level); over an edited or opened level it is one undo step back to that."""
        spec, size = levelio.parse(data, filename)
        self._cancel()
        base = self.spec is self._start_spec and not self.can_undo and not self.can_redo
        if refusal := self._commit(spec, size, selection=[]):
            raise EditorError(refusal)
        if base:
            self.history.undo_stack.clear()

    def export(self, format: str = "ours") -> str:
        return levelio.export(self.level_file(), format)

    def export_notes(self, format: str = "ours") -> list[str]:
        """What the export does and what the public tools do differently with the file: for Kinetix, what was
        split and the size class written, then notes (levelio.export_notes)."""
        return levelio.export_notes(self.level_file(), format)

    def export_with_notes(self, format: str = "ours") -> tuple[str, list[str]]:
        """(export(format), export_notes(format)) from one export."""
        return levelio.export_with_notes(self.level_file(), format)

    # ------------------------------------------------------------ keys and overlay

    def key(self, key: str, *, ctrl: bool = False, shift: bool = False, alt: bool = False, meta: bool = False) -> bool:
        k = key.lower() if len(key) == 1 else key
        command = ctrl or meta
        if command and k == "z":
            self.redo() if shift else self.undo()
        elif command and k == "y":
            self.redo()
        elif command and k == "c":
            self.copy()
        elif command and k == "v":
            self.paste()
        elif command and k == "d":
            self.duplicate_selection()
        elif command:
            return False
        elif key in ("Delete", "Backspace") and self._points:
            self._points.pop()  # while drawing a polygon: take back the last vertex
            self._bump()
        elif key in ("Delete", "Backspace"):
            self.delete_selection()
        elif key == "Escape":
            self._cancel()
            self.selection = []
            self.message, self.size_offer, self._retry = None, None, None  # Esc dismisses a refusal too
            self._bump()
        elif key == "Enter":
            if not self._points:
                return False
            self.finish_polygon()
        elif k == "r":
            self.rotate_selection(-15.0 if shift else 15.0)
        elif key in ("+", "="):
            self.scale_selection(1.1)
        elif key in ("-", "_"):
            self.scale_selection(1 / 1.1)
        else:
            return False
        return True

    def overlay(self) -> Overlay:
        preview: list[dict] = []
        press = self._press or {}
        kind = press.get("kind")
        if kind == "circle" and press.get("end") is not None:
            preview.append({"kind": "circle", "center": press["start"],
                            "radius": math.dist(press["start"], press["end"])})
        elif kind in ("rectangle", "box") and press.get("end") is not None:
            (x0, y0), (x1, y1) = press["start"], press["end"]
            preview.append({"kind": "polygon", "points": [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]})
        elif kind == "thruster" and press.get("end") is not None:
            preview.append({"kind": "arrow", "a": press["start"], "b": press["end"]})
        if self._points:
            pts = self._points + ([self._hover] if self._hover is not None else [])
            preview += [{"kind": "point", "at": q} for q in self._points]
            preview += [{"kind": "segment", "a": a, "b": b} for a, b in zip(pts, pts[1:], strict=False)]
        elif self._hover is not None and self.tool != "select" and not press:
            preview.append({"kind": "point", "at": self._hover})
        outlines = []
        for item, i in self.selection:
            if item == "body":
                outlines.append(outline(self.spec.bodies[i]))
            elif item == "joint":
                outlines.append({"kind": "point", "at": sel.joint_point(self.spec, self.spec.joints[i])})
            else:
                t = self.spec.thrusters[i]
                a = sel.thruster_point(self.spec, t)
                d = rotate((0.3, 0.0), sel.thruster_world_angle(self.spec, t))
                outlines.append({"kind": "arrow", "a": a, "b": (a[0] + d[0], a[1] + d[1])})
        return Overlay(preview, outlines, list(self._guides), self._snap_point, self.message)
