"""The pointer on the canvas: hover, press, drag and release, click and box select, turned into edits by the tool in
use (select, move and turn; draw circles, rectangles, polygons; place joints and thrusters), with snapping.
Editor (server.editor.editor) inherits it; the constants below are the gestures' own."""

from __future__ import annotations

import copy
import math

from kinetix.formats import BodySpec, JointSpec, ThrusterSpec
from server.editor import selection as sel
from server.editor.geometry import Point, contains, convexity_error, polygon_body, to_local
from server.editor.snapping import snap

DRAG_THRESHOLD = 0.02  # m: a press and release closer than this is a click
CYCLE_DISTANCE = 0.03  # m: clicks this close count as "the same spot" and cycle through what is under them
DEFAULT_RADIUS = 0.2  # a click with the circle tool (no drag) makes a circle of this radius
DEFAULT_SIDE = 0.4  # and with the rectangle tool, a square of this side
MIN_SIZE = 0.02  # m: smaller circles and rectangles are refused
# m: a point snaps to a feature (a vertex, a centre, the top of a circle) or aligns with one only this close. The
# browser session sets Editor.snap_radius from its canvas (server.play.session.SNAP_PIXELS on screen); 0.08 m
# (11 pixels on a 1280 x 800 page) moved a hinge from the click to a circle's top 10 pixels away (issue 37).
SNAP_RADIUS = 0.04


class PointerGestures:
    """Mixed into Editor: the pointer's gestures and the shapes, joints and thrusters the drawing tools add."""

    def _snap(self, p: Point, exclude: set[int] = frozenset()) -> Point:
        """p snapped (when snapping is on), remembering the guides for the overlay."""
        if not self.snapping:
            self._guides, self._snap_point = [], None
            return p
        bodies = [(i, b) for i, b in enumerate(self.spec.bodies) if i not in exclude]
        q, self._guides, self._snap_point = snap(p, bodies, self.grid, self.snap_radius)
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
