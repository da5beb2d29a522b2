"""Pure operations on a `LevelSpec` for the select tool: hit tests, assemblies, transforms, delete, copy.

Items are ("body", i), ("joint", i) or ("thruster", i), indices into the spec's lists. The first
`walls` bodies are the standard walls: never hit, moved, deleted or copied.
Every function that edits takes a spec it may change in place (the editor passes a copy).
"""

from __future__ import annotations

import copy
import math

from kinetix.formats import BodySpec, JointSpec, LevelSpec, ThrusterSpec
from kinetix.level import NUM_WALLS
from server.editor.geometry import Point, bounds, contains, rotate, to_world

Item = tuple[str, int]
MARKER_RADIUS = 0.08  # m: how close a click must be to a joint or thruster marker


def wall_count(spec: LevelSpec) -> int:
    """How many leading bodies are the standard walls (fixed polygons in slots 0-3), else 0."""
    first = spec.bodies[:NUM_WALLS]
    if len(first) == NUM_WALLS and all(b.shape == "polygon" and b.fixed for b in first):
        return NUM_WALLS
    return 0


def joint_point(spec: LevelSpec, joint: JointSpec) -> Point:
    return to_world(spec.bodies[joint.a], joint.anchor_a)


def thruster_point(spec: LevelSpec, thruster: ThrusterSpec) -> Point:
    return to_world(spec.bodies[thruster.body], thruster.anchor)


def thruster_world_angle(spec: LevelSpec, thruster: ThrusterSpec) -> float:
    return spec.bodies[thruster.body].angle + thruster.angle


def hits(spec: LevelSpec, p: Point) -> list[Item]:
    """Everything under p, the topmost first: thrusters, joints, then bodies last drawn first."""
    out: list[Item] = []
    out += [("thruster", k) for k, t in enumerate(spec.thrusters) if math.dist(thruster_point(spec, t), p)
            <= MARKER_RADIUS]
    out += [("joint", k) for k, j in enumerate(spec.joints) if math.dist(joint_point(spec, j), p) <= MARKER_RADIUS]
    walls = wall_count(spec)
    out += [("body", i) for i in reversed(range(walls, len(spec.bodies))) if contains(spec.bodies[i], p)]
    return out


def bodies_at(spec: LevelSpec, p: Point, include_walls: bool = True) -> list[int]:
    """Bodies containing p, the topmost (last) first; walls last."""
    walls = wall_count(spec)
    inside = [i for i in reversed(range(len(spec.bodies))) if contains(spec.bodies[i], p)]
    if not include_walls:
        inside = [i for i in inside if i >= walls]
    return [i for i in inside if i >= walls] + [i for i in inside if i < walls]


def in_box(spec: LevelSpec, x0: float, y0: float, x1: float, y1: float) -> list[Item]:
    """Items wholly inside the box (bodies by their bounds, markers by their point)."""
    lo_x, hi_x, lo_y, hi_y = min(x0, x1), max(x0, x1), min(y0, y1), max(y0, y1)

    def inside(p):
        return lo_x <= p[0] <= hi_x and lo_y <= p[1] <= hi_y

    walls = wall_count(spec)
    out: list[Item] = []
    for i in range(walls, len(spec.bodies)):
        bx0, by0, bx1, by1 = bounds(spec.bodies[i])
        if inside((bx0, by0)) and inside((bx1, by1)):
            out.append(("body", i))
    out += [("joint", k) for k, j in enumerate(spec.joints) if inside(joint_point(spec, j))]
    out += [("thruster", k) for k, t in enumerate(spec.thrusters) if inside(thruster_point(spec, t))]
    return out


def selected_bodies(spec: LevelSpec, selection: list[Item]) -> set[int]:
    """Bodies the selection stands for: selected bodies and the bodies of selected joints (not walls)."""
    walls = wall_count(spec)
    out = {i for kind, i in selection if kind == "body"}
    for kind, k in selection:
        if kind == "joint":
            out |= {spec.joints[k].a, spec.joints[k].b}
    return {i for i in out if i >= walls}


def assembly(spec: LevelSpec, bodies: set[int]) -> set[int]:
    """The bodies plus everything connected to them through joints, never crossing a wall."""
    walls = wall_count(spec)
    out, todo = set(bodies), list(bodies)
    while todo:
        i = todo.pop()
        for joint in spec.joints:
            for here, there in ((joint.a, joint.b), (joint.b, joint.a)):
                if here == i and there >= walls and there not in out:
                    out.add(there)
                    todo.append(there)
    return out


def move(spec: LevelSpec, bodies: set[int], dx: float, dy: float) -> None:
    for i in bodies:
        b = spec.bodies[i]
        b.position = (b.position[0] + dx, b.position[1] + dy)


def pivot(spec: LevelSpec, bodies: set[int]) -> Point:
    boxes = [bounds(spec.bodies[i]) for i in bodies]
    return ((min(b[0] for b in boxes) + max(b[2] for b in boxes)) / 2,
            (min(b[1] for b in boxes) + max(b[3] for b in boxes)) / 2)


def rotate_bodies(spec: LevelSpec, bodies: set[int], radians: float, about: Point) -> None:
    # Body-frame anchors and the relative angles of joints stay as they are: the whole assembly turns.
    for i in bodies:
        b = spec.bodies[i]
        rx, ry = rotate((b.position[0] - about[0], b.position[1] - about[1]), radians)
        b.position = (about[0] + rx, about[1] + ry)
        b.angle = b.angle + radians


def scale_bodies(spec: LevelSpec, bodies: set[int], factor: float, about: Point) -> None:
    for i in bodies:
        b = spec.bodies[i]
        b.position = (about[0] + (b.position[0] - about[0]) * factor, about[1] + (b.position[1] - about[1]) * factor)
        if b.shape == "circle":
            b.radius = b.radius * factor
        else:
            b.vertices = [[x * factor, y * factor] for x, y in b.vertices]
    for joint in spec.joints:
        if joint.a in bodies and joint.b in bodies:
            joint.anchor_a = (joint.anchor_a[0] * factor, joint.anchor_a[1] * factor)
            joint.anchor_b = (joint.anchor_b[0] * factor, joint.anchor_b[1] * factor)
    for thruster in spec.thrusters:
        if thruster.body in bodies:
            thruster.anchor = (thruster.anchor[0] * factor, thruster.anchor[1] * factor)


def renumber(spec: LevelSpec) -> None:
    """Paths name each item's index, so build's error messages point at the right one."""
    for kind in ("bodies", "joints", "thrusters"):
        for k, item in enumerate(getattr(spec, kind)):
            item.path = f"{kind}[{k}]"


def delete(spec: LevelSpec, selection: list[Item]) -> None:
    """Remove the selected items; a removed body takes its joints and thrusters with it."""
    walls = wall_count(spec)
    gone = {i for kind, i in selection if kind == "body" and i >= walls}
    gone_joints = {k for kind, k in selection if kind == "joint"}
    gone_thrusters = {k for kind, k in selection if kind == "thruster"}
    new_index, n = {}, 0
    for i in range(len(spec.bodies)):
        if i not in gone:
            new_index[i] = n
            n += 1
    joints = []
    for k, joint in enumerate(spec.joints):
        if k not in gone_joints and joint.a in new_index and joint.b in new_index:
            joint.a, joint.b = new_index[joint.a], new_index[joint.b]
            joints.append(joint)
    thrusters = []
    for k, thruster in enumerate(spec.thrusters):
        if k not in gone_thrusters and thruster.body in new_index:
            thruster.body = new_index[thruster.body]
            thrusters.append(thruster)
    spec.bodies = [b for i, b in enumerate(spec.bodies) if i not in gone]
    spec.joints, spec.thrusters = joints, thrusters
    renumber(spec)


Clip = tuple[list[BodySpec], list[JointSpec], list[ThrusterSpec]]


def copy_items(spec: LevelSpec, selection: list[Item]) -> Clip:
    """The selected bodies (and those of selected joints and thrusters) with the joints between them
    and their thrusters, re-indexed among themselves."""
    chosen = selected_bodies(spec, selection)
    walls = wall_count(spec)
    chosen |= {spec.thrusters[k].body for kind, k in selection if kind == "thruster"
               and spec.thrusters[k].body >= walls}
    order = sorted(chosen)
    index = {i: n for n, i in enumerate(order)}
    bodies = [copy.deepcopy(spec.bodies[i]) for i in order]
    joints = []
    for joint in spec.joints:
        if joint.a in index and joint.b in index:
            j = copy.deepcopy(joint)
            j.a, j.b = index[joint.a], index[joint.b]
            joints.append(j)
    thrusters = []
    for thruster in spec.thrusters:
        if thruster.body in index:
            t = copy.deepcopy(thruster)
            t.body = index[thruster.body]
            thrusters.append(t)
    return bodies, joints, thrusters


def paste(spec: LevelSpec, clip: Clip, dx: float, dy: float) -> list[Item]:
    """Append a copy of the clip moved by (dx, dy); returns the new items."""
    bodies, joints, thrusters = copy.deepcopy(clip)
    base, jbase, tbase = len(spec.bodies), len(spec.joints), len(spec.thrusters)
    for b in bodies:
        b.position = (b.position[0] + dx, b.position[1] + dy)
    for j in joints:
        j.a, j.b = j.a + base, j.b + base
    for t in thrusters:
        t.body += base
    spec.bodies += bodies
    spec.joints += joints
    spec.thrusters += thrusters
    renumber(spec)
    return ([("body", base + n) for n in range(len(bodies))] + [("joint", jbase + n) for n in range(len(joints))]
            + [("thruster", tbase + n) for n in range(len(thrusters))])
