"""Drawing tools, joints and thrusters, and the size-class refusals of the editor model."""

import math

import pytest

from kinetix.formats import build
from server.editor import Editor
from tests.server.editor.scenes import blank_editor, drag


@pytest.fixture
def ed() -> Editor:
    return blank_editor()


def test_new_editor_is_walls_only(ed):
    assert len(ed.spec.bodies) == 4 and all(b.fixed for b in ed.spec.bodies)
    assert ed.limits() == {"polygons": (4, 12), "circles": (0, 4), "joints": (0, 6), "thrusters": (0, 2)}
    assert not ed.can_undo


def test_circle_press_centre_drag_radius(ed):
    ed.set_tool("circle")
    assert drag(ed, (1.0, 2.0), (1.3, 2.4)) is None
    body = ed.spec.bodies[-1]
    assert body.shape == "circle" and body.position == (1.0, 2.0)
    assert body.radius == pytest.approx(0.5)
    assert ed.selection == [("body", 4)]
    assert ed.level_file().level.sim.bodies.active.sum() == 5


def test_circle_preview_while_dragging(ed):
    ed.set_tool("circle")
    ed.pointer_down(1.0, 1.0)
    ed.pointer_move(1.0, 1.6)
    preview = ed.overlay().preview
    assert preview == [{"kind": "circle", "center": (1.0, 1.0), "radius": pytest.approx(0.6)}]
    ed.pointer_up(1.0, 1.6)
    assert ed.overlay().preview == []


def test_rectangle_drag_any_direction(ed):
    ed.set_tool("rectangle")
    drag(ed, (2.0, 2.0), (1.0, 1.5))
    body = ed.spec.bodies[-1]
    assert body.shape == "polygon"
    assert body.position == pytest.approx((1.5, 1.75))
    xs = sorted(v[0] for v in body.vertices)
    ys = sorted(v[1] for v in body.vertices)
    assert xs == pytest.approx([-0.5, -0.5, 0.5, 0.5]) and ys == pytest.approx([-0.25, -0.25, 0.25, 0.25])


def test_triangle_closes_at_three_vertices(ed):
    ed.set_tool("triangle")
    assert ed.click(1.0, 1.0) is None
    ed.click(2.0, 1.0)
    assert len(ed.spec.bodies) == 4 and len(ed.overlay().preview) > 0
    ed.click(1.5, 2.0)
    body = ed.spec.bodies[-1]
    assert body.shape == "polygon" and len(body.vertices) == 3
    assert body.position == pytest.approx((1.5, 4 / 3))


def test_polygon_closes_with_enter_or_first_vertex(ed):
    ed.set_tool("polygon")
    # clockwise clicks: stored counter-clockwise anyway
    for p in [(1.0, 1.0), (1.0, 2.0), (2.0, 2.5), (3.0, 2.0), (3.0, 1.0)]:
        ed.click(*p)
    assert ed.key("Enter")
    body = ed.spec.bodies[-1]
    assert len(body.vertices) == 5
    area = sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(body.vertices, body.vertices[1:] + body.vertices[:1],
                                                        strict=True))
    assert area > 0
    for p in [(3.5, 3.0), (4.5, 3.0), (4.5, 4.0), (3.5, 3.0)]:
        ed.click(*p)
    assert len(ed.spec.bodies) == 6 and len(ed.spec.bodies[-1].vertices) == 3


def test_non_convex_polygon_rejected(ed):
    ed.set_tool("polygon")
    for p in [(1.0, 1.0), (3.0, 1.0), (2.0, 1.5), (3.0, 3.0), (1.0, 3.0)]:
        ed.click(*p)
    assert ed.finish_polygon() == "polygon is not convex"
    assert len(ed.spec.bodies) == 4 and not ed.can_undo
    assert ed.overlay().message == "polygon is not convex"


def test_polygon_vertex_limit(ed):
    ed.set_tool("polygon")
    centre, r = (2.5, 2.5), 1.0
    for k in range(9):
        angle = 2 * math.pi * k / 9
        message = ed.click(centre[0] + r * math.cos(angle), centre[1] + r * math.sin(angle))
    assert message is not None and "too many vertices" in message
    ed.finish_polygon()
    assert len(ed.spec.bodies[-1].vertices) == 8


def make_pair(ed):
    ed.set_tool("rectangle")
    drag(ed, (1.0, 1.0), (2.0, 1.4))
    ed.set_tool("circle")
    drag(ed, (2.0, 1.2), (2.3, 1.2))


@pytest.mark.parametrize("tool", ["revolute", "fixed"])
def test_joint_where_two_bodies_overlap(ed, tool):
    make_pair(ed)
    ed.set_tool(tool)
    assert ed.click(1.95, 1.2) is None
    (joint,) = ed.spec.joints
    assert (joint.a, joint.b) == (4, 5) and joint.fixed == (tool == "fixed")
    assert joint.anchor_a == pytest.approx((0.45, 0.0)) and joint.anchor_b == pytest.approx((-0.05, 0.0))
    build(ed.spec, ed.size)


def test_joint_needs_two_bodies(ed):
    make_pair(ed)
    ed.set_tool("revolute")
    message = ed.click(1.2, 1.2)
    assert "two bodies" in message and ed.spec.joints == []


def test_joint_to_a_wall_allowed(ed):
    ed.set_tool("circle")
    drag(ed, (2.5, 0.5), (2.5, 0.8))
    ed.set_tool("revolute")
    assert ed.click(2.5, 0.35) is None
    assert (ed.spec.joints[0].a, ed.spec.joints[0].b) == (0, 4)


def test_thruster_click_and_aim(ed):
    make_pair(ed)
    ed.set_tool("thruster")
    drag(ed, (1.5, 1.2), (1.5, 0.5))
    (thruster,) = ed.spec.thrusters
    assert thruster.body == 4 and thruster.anchor == pytest.approx((0.0, 0.0))
    assert thruster.angle == pytest.approx(-math.pi / 2)
    assert ed.click(0.5, 4.0) is not None  # not on a body
    assert len(ed.spec.thrusters) == 1


def test_overflow_refused_with_message():
    ed = Editor(size="s")
    ed.snapping = False
    ed.set_tool("circle")
    assert ed.click(1.0, 2.0) is None
    assert ed.click(2.0, 2.0) is None
    assert ed.click(3.0, 2.0).startswith("no circle left: 2 of 2 used in size s")
    assert ed.limits()["circles"] == (2, 2)
    ed.set_tool("revolute")
    ed.set_tool("rectangle")
    ed.click(1.0, 3.5)
    assert ed.click(3.0, 3.5).startswith("no polygon left: 5 of 5 used in size s")


def test_joint_and_thruster_overflow():
    ed = Editor(size="s")
    ed.snapping = False
    make_pair(ed)
    ed.set_tool("revolute")
    ed.click(1.95, 1.2)
    assert ed.click(1.95, 1.2).startswith("no joint left: 1 of 1 used in size s")
    ed.set_tool("thruster")
    ed.click(1.5, 1.2)
    assert ed.click(1.5, 1.2).startswith("no thruster left: 1 of 1 used in size s")


def test_a_full_level_is_offered_the_next_size_and_moving_there_does_the_refused_edit():
    ed = Editor(size="m")
    ed.snapping = False
    ed.set_tool("polygon")
    squares = [[(x, 3.0), (x + 0.4, 3.0), (x + 0.4, 3.4), (x, 3.4)] for x in (0.5, 1.5, 2.5)]
    for square in squares[:2]:
        for p in square:
            ed.click(*p)
        ed.key("Enter")
    for p in squares[2]:
        ed.click(*p)
    ed.key("Enter")
    assert ed.message == 'no polygon left: 6 of 6 used in size m; "Move to size l" in the panel makes room'
    assert ed.size_offer == "l" and ed.limits()["polygons"] == (6, 6)
    assert ed.grow_size() is None
    assert ed.size.name == "l" and ed.limits()["polygons"] == (7, 12)  # moved, and the third square is drawn
    assert ed.spec.bodies[-1].position == pytest.approx((2.7, 3.2))
    assert ed.size_offer is None and ed.message is None
    ed.undo()  # the square, then the move: two steps
    assert ed.size.name == "l" and ed.limits()["polygons"] == (6, 12)
    ed.undo()
    assert ed.size.name == "m"


def test_a_full_l_level_is_offered_xl_and_nothing_beyond_xl():
    ed = Editor(size="s")
    ed.set_size("l")
    ed.snapping = False
    ed.set_tool("circle")
    for x in (0.5, 1.5, 2.5, 3.5):
        assert ed.click(x, 2.0) is None
    assert ed.click(4.5, 2.0) == 'no circle left: 4 of 4 used in size l; "Move to size xl" in the panel makes room'
    assert ed.size_offer == "xl"
    assert ed.grow_size() is None
    assert ed.size.name == "xl" and ed.limits()["circles"] == (5, 16)
    for x, y in [(x, y) for y in (1.0, 3.0) for x in (0.5, 1.5, 2.5, 3.5, 4.5, 0.9)][:11]:
        assert ed.click(x, y + (0.8 if x == 0.9 else 0.0)) is None
    assert ed.limits()["circles"] == (16, 16)
    assert ed.click(4.2, 4.2) == "no circle left: 16 of 16 used in size xl" and ed.size_offer is None
    assert ed.grow_size().startswith("no larger size class")


def test_unknown_tool(ed):
    from server.editor import EditorError
    with pytest.raises(EditorError, match="unknown tool"):
        ed.set_tool("laser")


def test_revision_bumps(ed):
    r = ed.revision
    ed.set_tool("circle")
    assert ed.revision > r
    r = ed.revision
    ed.click(1.0, 1.0)
    assert ed.revision > r


def test_polygon_backspace_and_escape(ed):
    ed.set_tool("polygon")
    for p in [(1.0, 1.0), (2.0, 1.0), (1.7, 1.2), (2.0, 2.0)]:
        ed.click(*p)
    assert ed.key("Backspace")  # takes back (2, 2)
    assert ed.key("Backspace")  # and (1.7, 1.2), the dent
    ed.click(2.0, 2.0)
    ed.click(1.0, 2.0)
    ed.key("Enter")
    assert len(ed.spec.bodies) == 5 and len(ed.spec.bodies[-1].vertices) == 4
    ed.click(3.0, 3.0)
    ed.key("Escape")
    assert ed.overlay().preview == [] or all(s["kind"] == "point" for s in ed.overlay().preview)
    ed.click(3.0, 3.0)
    ed.click(4.0, 3.0)
    assert ed.key("Enter") and len(ed.spec.bodies) == 5  # only 2 vertices since Escape: refused
    assert "at least 3" in ed.overlay().message


def test_joint_and_thruster_snap_only_where_it_stays_on_the_bodies(ed):
    make_pair(ed)
    ed.snapping = True
    ed.grid = 0.5
    ed.set_tool("revolute")
    ed.click(1.97, 1.22)  # near the circle's centre (2, 1.2), which lies on both bodies
    assert ed.spec.joints[0].anchor_b == pytest.approx((0.0, 0.0))
    ed.set_tool("thruster")
    # x to the grid (1.0), y aligned with the centres (1.2): the left edge's midpoint, still on the body
    ed.click(1.18, 1.17)  # (within the snap radius, 0.04 m, of the centres' y)
    assert ed.spec.thrusters[0].anchor == pytest.approx((-0.5, 0.0))
    ed.click(1.3, 1.3)  # to the grid point (1.5, 1.5): off the body, so not snapped
    assert ed.spec.thrusters[1].anchor == pytest.approx((-0.2, 0.1))
