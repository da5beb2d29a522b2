"""The editor's document: the level being edited, its history, the tool in use, the selection and the overlay.

Every edit builds a candidate `LevelSpec`, checks it with `kinetix.formats.build` in the current size
class, and only then replaces the level and records one undo step; a refused edit changes nothing
and leaves a message. The 4 standard walls are part of the level but not of the editing: they
cannot be selected, moved or deleted (they can be the other end of a joint, e.g. to pin a body).
Not thread-safe on its own: the server session calls it under its lock.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable

from kinetix.formats import BodySpec, JointSpec, LevelSpec, ThrusterSpec, build
from kinetix.level import SIZES, LevelError, LevelFile, SizeClass, size_class
from kinetix.ranges import RANGES
from server.editor import levelio, properties
from server.editor import selection as sel
from server.editor.geometry import Point, contains, convexity_error, outline, polygon_body, rotate, to_local
from server.editor.history import History, Snapshot
from server.editor.levelio import EditorError
from server.editor.snapping import snap

TOOLS = ("select", "circle", "rectangle", "triangle", "polygon", "revolute", "fixed", "thruster")
DRAG_THRESHOLD = 0.02  # m: a press and release closer than this is a click
CYCLE_DISTANCE = 0.03  # m: clicks this close count as "the same spot" and cycle through what is under them
PASTE_OFFSET = (0.25, -0.25)
DEFAULT_RADIUS = 0.2  # a click with the circle tool (no drag) makes a circle of this radius
DEFAULT_SIDE = 0.4  # and with the rectangle tool, a square of this side
MIN_SIZE = 0.02  # m: smaller circles and rectangles are refused
CAPACITY_NAMES = {"polygons": "polygon", "circles": "circle", "joints": "joint", "thrusters": "thruster"}
GROWTH = {"s": "m", "m": "l"}  # the next larger size class a full level is offered (none after l or a custom size)


@dataclasses.dataclass
class Overlay:
    """What the renderer draws on top of the level, all in world coordinates."""

    preview: list[dict] = dataclasses.field(default_factory=list)
    selection: list[dict] = dataclasses.field(default_factory=list)
    guides: list[tuple[float, float, float, float]] = dataclasses.field(default_factory=list)
    snap_point: tuple[float, float] | None = None
    message: str | None = None


class Editor:
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

    def _snap(self, p: Point, exclude: set[int] = frozenset()) -> Point:
        """p snapped (when snapping is on), remembering the guides for the overlay."""
        if not self.snapping:
            self._guides, self._snap_point = [], None
            return p
        bodies = [(i, b) for i, b in enumerate(self.spec.bodies) if i not in exclude]
        q, self._guides, self._snap_point = snap(p, bodies, self.grid)
        return q

    def _snap_inside(self, p: Point, body: int) -> Point:
        """p snapped, unless snapping would take it off the body."""
        q = self._snap(p)
        return q if contains(self.spec.bodies[body], q) else p

    def hover(self, x: float, y: float) -> None:
        if self.tool == "select":
            return
        before = (self._hover, self._snap_point, tuple(self._guides))
        self._hover = self._snap((x, y))
        if (self._hover, self._snap_point, tuple(self._guides)) != before:
            self._bump()

    def pointer_down(self, x: float, y: float, *, shift: bool = False, ctrl: bool = False, alt: bool = False,
                     meta: bool = False) -> str | None:
        raw = (x, y)
        if self.tool == "select":
            self._press = {"kind": "press", "start": raw, "shift": shift, "alt": alt, "ctrl": ctrl or meta}
        elif self.tool in ("circle", "rectangle"):
            self._press = {"kind": self.tool, "start": self._snap(raw), "end": None, "raw": raw}
        elif self.tool == "thruster":
            bodies = sel.bodies_at(self.spec, raw, include_walls=False)
            if not bodies:
                return self._say("press on a body to place a thruster, then drag to aim it")
            at = self._snap_inside(raw, bodies[0])
            self._press = {"kind": "thruster", "start": at, "body": bodies[0], "end": None, "raw": raw}
        else:  # polygons and joints act on clicks
            self._press = {"kind": "click", "raw": raw}
        self._bump()
        return None

    def pointer_move(self, x: float, y: float, **mods) -> str | None:
        press = self._press
        if press is None:
            self.hover(x, y)
            return None
        p = (x, y)
        if press["kind"] == "press":
            if math.dist(p, press["start"]) < DRAG_THRESHOLD:
                return None
            self._start_drag(press)
            press = self._press
        if press["kind"] == "move":
            self._drag_move(press, p)
        elif press["kind"] in ("rotate", "scale"):
            self._drag_turn(press, p)
        elif press["kind"] == "box":
            press["end"] = p
        elif press["kind"] in ("circle", "rectangle", "thruster"):
            press["end"] = self._snap(p)
        self._bump()
        return None

    def _start_drag(self, press: dict) -> None:
        """A select-tool press became a drag: move what is under it (or the selection), or draw a box."""
        start = press["start"]
        under = sel.hits(self.spec, start)
        if under and not any(item in self.selection for item in under):
            top = under[0]
            self.selection = (self.selection + [top]) if press["shift"] else [top]
        if any(item in self.selection for item in under):
            moving = sel.assembly(self.spec, sel.selected_bodies(self.spec, self.selection))
            only_thrusters = not moving and any(k == "thruster" for k, _ in self.selection)
            if moving and (press["alt"] or press["ctrl"]):
                self._press = {"kind": "rotate" if press["alt"] else "scale", "start": start, "bodies": moving,
                               "before": self._snapshot(), "origin": copy.deepcopy(self.spec),
                               "pivot": sel.pivot(self.spec, moving)}
                return
            if moving or only_thrusters:
                grab = self.spec.bodies[min(moving)].position if moving else start
                self._press = {"kind": "move", "start": start, "bodies": moving, "before": self._snapshot(),
                               "origin": copy.deepcopy(self.spec), "grab": tuple(grab)}
                return
        self._press = {"kind": "box", "start": start, "end": start, "add": press["shift"]}

    def _drag_move(self, press: dict, p: Point) -> None:
        dx, dy = p[0] - press["start"][0], p[1] - press["start"][1]
        gx, gy = press["grab"]
        sx, sy = self._snap((gx + dx, gy + dy), exclude=press["bodies"])
        dx, dy = sx - gx, sy - gy
        spec = copy.deepcopy(press["origin"])
        if press["bodies"]:
            sel.move(spec, press["bodies"], dx, dy)
        else:  # thrusters alone slide over their bodies
            for kind, k in self.selection:
                if kind == "thruster":
                    t = spec.thrusters[k]
                    body = spec.bodies[t.body]
                    ox, oy = sel.thruster_point(spec, t)
                    t.anchor = to_local(body, (ox + dx, oy + dy))
        self.spec = spec  # live, uncommitted: pointer_up validates it and records one undo step

    def _drag_turn(self, press: dict, p: Point) -> None:
        """Alt+drag turns the selection's assembly about its centre (15 degree steps when snapping);
        Ctrl+drag resizes it by the ratio of distances from the centre."""
        (cx, cy), (sx, sy) = press["pivot"], press["start"]
        spec = copy.deepcopy(press["origin"])
        if press["kind"] == "rotate":
            turn = math.atan2(p[1] - cy, p[0] - cx) - math.atan2(sy - cy, sx - cx)
            if self.snapping:
                turn = math.radians(round(math.degrees(turn) / 15.0) * 15.0)
            sel.rotate_bodies(spec, press["bodies"], turn, press["pivot"])
        else:
            factor = math.dist(p, press["pivot"]) / max(math.dist(press["start"], press["pivot"]), 1e-6)
            sel.scale_bodies(spec, press["bodies"], max(factor, 0.05), press["pivot"])
        self.spec = spec

    def pointer_up(self, x: float, y: float, **mods) -> str | None:
        press, self._press = self._press, None
        if press is None:
            return None
        p = (x, y)
        kind = press["kind"]
        if kind in ("press", "click"):
            return self.click(x, y, **mods)
        if kind in ("move", "rotate", "scale"):
            if kind == "move":
                self._drag_move(press, p)
            else:
                self._drag_turn(press, p)
            moved, self.spec = self.spec, press["origin"]
            if moved == press["origin"]:
                self._bump()
                return None
            return self._commit(moved, before=press["before"])
        if kind == "box":
            self.box_select(*press["start"], x, y, add=press["add"])
            return None
        end = self._snap(p)
        if math.dist(press.get("raw", press["start"]), p) < DRAG_THRESHOLD:
            end = None  # a click: default size or direction
        if kind == "circle":
            return self._add_circle(press["start"], end)
        if kind == "rectangle":
            return self._add_rectangle(press["start"], end)
        return self._add_thruster(press["body"], press["start"], end)

    def click(self, x: float, y: float, *, shift: bool = False, ctrl: bool = False, alt: bool = False,
              meta: bool = False) -> str | None:
        self._press = None
        p = (x, y)
        if self.tool == "select":
            return self._click_select(p, shift)
        q = self._snap(p)
        if self.tool == "circle":
            return self._add_circle(q, None)
        if self.tool == "rectangle":
            return self._add_rectangle(q, None)
        if self.tool in ("triangle", "polygon"):
            return self._add_vertex(q)
        if self.tool in ("revolute", "fixed"):
            # The snapped point (e.g. a wheel's centre) if it still lies on two bodies, else where clicked.
            return self._add_joint(q if len(sel.bodies_at(self.spec, q)) >= 2 else p, fixed=self.tool == "fixed")
        bodies = sel.bodies_at(self.spec, p, include_walls=False)
        if not bodies:
            return self._say("click on a body to place a thruster")
        return self._add_thruster(bodies[0], self._snap_inside(p, bodies[0]), None)

    def _click_select(self, p: Point, shift: bool) -> str | None:
        under = sel.hits(self.spec, p)
        if not under:
            self._last_click = None
            if not shift:
                self.selection = []
            self._bump()
            return None
        index = 0
        if self._last_click is not None:
            where, previous, k = self._last_click
            if math.dist(where, p) <= CYCLE_DISTANCE and previous == under:
                index = (k + 1) % len(under)
        self._last_click = (p, under, index)
        item = under[index]
        if shift:
            self.selection = [s for s in self.selection if s != item] if item in self.selection \
                else self.selection + [item]
        else:
            self.selection = [item]
        self._bump()
        return None

    def box_select(self, x0: float, y0: float, x1: float, y1: float, *, add: bool = False) -> None:
        found = sel.in_box(self.spec, x0, y0, x1, y1)
        self.selection = list(dict.fromkeys((self.selection if add else []) + found))
        self._bump()

    # ------------------------------------------------------------ making things

    def _add_body(self, body: BodySpec) -> str | None:
        kind = "circles" if body.shape == "circle" else "polygons"
        if refusal := self._room(kind, retry=lambda: self._add_body(body)):
            return refusal
        if body.shape == "polygon" and len(body.vertices) > self.size.max_vertices:
            return self._say(f"too many vertices: {len(body.vertices)}, size {self.size.name} allows "
                             f"{self.size.max_vertices}")
        spec = self._candidate()
        spec.bodies.append(body)
        return self._commit(spec, selection=[("body", len(spec.bodies) - 1)])

    def _add_circle(self, centre: Point, edge: Point | None) -> str | None:
        radius = DEFAULT_RADIUS if edge is None else math.dist(centre, edge)
        if radius < MIN_SIZE:
            return self._say(f"circle too small: radius {radius:.3f} m < {MIN_SIZE} m")
        return self._add_body(BodySpec(path="", shape="circle", position=tuple(centre), radius=radius))

    def _add_rectangle(self, a: Point, b: Point | None) -> str | None:
        if b is None:
            h = DEFAULT_SIDE / 2
            a, b = (a[0] - h, a[1] - h), (a[0] + h, a[1] + h)
        x0, x1, y0, y1 = min(a[0], b[0]), max(a[0], b[0]), min(a[1], b[1]), max(a[1], b[1])
        if x1 - x0 < MIN_SIZE or y1 - y0 < MIN_SIZE:
            return self._say(f"rectangle too small: {x1 - x0:.3f} x {y1 - y0:.3f} m; drag a larger one")
        return self._add_body(polygon_body([(x0, y0), (x1, y0), (x1, y1), (x0, y1)]))

    def _add_vertex(self, q: Point) -> str | None:
        points = self._points
        if len(points) >= 3 and math.dist(q, points[0]) <= max(2 * DRAG_THRESHOLD, 0.05):
            return self.finish_polygon()
        if points and math.dist(q, points[-1]) < 1e-6:
            return self._say("that vertex is already placed")
        if self.tool == "polygon" and len(points) >= self.size.max_vertices:
            return self._say(f"too many vertices: size {self.size.name} allows {self.size.max_vertices}; "
                             "press Enter to finish")
        points.append(q)
        if self.tool == "triangle" and len(points) == 3:
            return self.finish_polygon()
        self._bump()
        return None

    def finish_polygon(self) -> str | None:
        points, self._points = self._points, []
        if len(points) < 3:
            return self._say(f"a polygon needs at least 3 vertices, got {len(points)}")
        if error := convexity_error(points):
            return self._say(error)
        return self._add_body(polygon_body(points))

    def _add_joint(self, p: Point, fixed: bool) -> str | None:
        if refusal := self._room("joints", retry=lambda: self._add_joint(p, fixed)):
            return refusal
        under = sel.bodies_at(self.spec, p)
        if len(under) < 2:
            return self._say("click where two bodies overlap to join them")
        # The lower index is body a (usually the one drawn first, the "parent").
        a, b = sorted(under[:2])
        spec = self._candidate()
        ba, bb = spec.bodies[a], spec.bodies[b]
        spec.joints.append(JointSpec(path="", a=a, b=b, anchor_a=to_local(ba, p), anchor_b=to_local(bb, p),
                                     ref_angle=bb.angle - ba.angle, fixed=fixed))
        return self._commit(spec, selection=[("joint", len(spec.joints) - 1)])

    def _add_thruster(self, body: int, at: Point, aim: Point | None) -> str | None:
        if refusal := self._room("thrusters", retry=lambda: self._add_thruster(body, at, aim)):
            return refusal
        b = self.spec.bodies[body]
        world = math.pi / 2 if aim is None or aim == at else math.atan2(aim[1] - at[1], aim[0] - at[0])
        spec = self._candidate()
        spec.thrusters.append(ThrusterSpec(path="", body=body, anchor=to_local(b, at), angle=world - b.angle))
        return self._commit(spec, selection=[("thruster", len(spec.thrusters) - 1)])

    # ------------------------------------------------------------ selection edits

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
        """What the public tools do differently with the exported file (e.g. 5-8-vertex polygons in Kinetix)."""
        return levelio.export_notes(self.level_file(), format)

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
