"""The select tool: click cycling, box select, drag-move of assemblies, rotate, resize, delete, copy and paste."""

import math

import pytest

from kinetix.formats import build
from server.editor import Editor
from tests.server.editor.scenes import drag, hinged_editor


@pytest.fixture
def ed() -> Editor:
    """Bodies 4 (rectangle) and 5 (circle) hinged at (1.95, 1.2), body 6 a lone circle, thruster on body 4."""
    return hinged_editor(lone_circle=True)


def test_click_selects_topmost_and_cycles(ed):
    ed.click(1.98, 1.3)  # inside the circle and the rectangle
    assert ed.selection == [("body", 5)]
    ed.click(1.98, 1.3)
    assert ed.selection == [("body", 4)]
    ed.click(1.99, 1.3)  # the same spot, give or take
    assert ed.selection == [("body", 5)]
    ed.click(0.5, 4.0)  # empty space clears
    assert ed.selection == []


def test_click_on_markers_and_shift(ed):
    ed.click(1.95, 1.2)
    assert ed.selection == [("joint", 0)]
    ed.click(1.2, 1.2)
    assert ed.selection == [("thruster", 0)]
    ed.click(3.5, 3.5, shift=True)
    assert ed.selection == [("thruster", 0), ("body", 6)]
    ed.click(3.5, 3.5, shift=True)
    assert ed.selection == [("thruster", 0)]


def test_walls_not_selectable(ed):
    ed.click(2.5, 0.2)  # inside the floor
    assert ed.selection == []
    ed.box_select(-10, -10, 20, 20)
    assert ("body", 0) not in ed.selection and ("body", 4) in ed.selection


def test_box_select_and_add(ed):
    ed.box_select(0.9, 0.9, 2.1, 1.5)
    assert set(ed.selection) == {("body", 4), ("joint", 0), ("thruster", 0)}
    ed.box_select(3.0, 3.0, 4.0, 4.0, add=True)
    assert ("body", 6) in ed.selection and ("body", 4) in ed.selection
    ed.box_select(3.0, 3.0, 4.0, 4.0)
    assert ed.selection == [("body", 6)]


def test_box_select_by_drag(ed):
    drag(ed, (3.0, 3.0), (4.0, 4.0))
    assert ed.selection == [("body", 6)]
    drag(ed, (0.9, 0.9), (2.1, 1.5), shift=True)
    assert ("body", 6) in ed.selection and ("body", 4) in ed.selection


def test_drag_moves_jointed_assembly_as_one_step(ed):
    before = [b.position for b in ed.spec.bodies]
    steps = len(ed.history.undo_stack)
    drag(ed, (1.5, 1.3), (2.0, 2.3))
    after = [b.position for b in ed.spec.bodies]
    assert after[4] == pytest.approx((before[4][0] + 0.5, before[4][1] + 1.0))
    assert after[5] == pytest.approx((before[5][0] + 0.5, before[5][1] + 1.0))  # jointed: moved too
    assert after[6] == before[6] and after[:4] == before[:4]
    assert len(ed.history.undo_stack) == steps + 1
    ed.undo()
    assert [b.position for b in ed.spec.bodies] == before


def test_drag_unselected_body_selects_and_moves_it(ed):
    ed.click(2.05, 1.25)
    drag(ed, (3.5, 3.5), (3.0, 3.0))
    assert ed.selection == [("body", 6)]
    assert ed.spec.bodies[6].position == pytest.approx((3.0, 3.0))


def test_drag_snaps_to_grid(ed):
    ed.snapping = True
    ed.grid = 0.5
    drag(ed, (3.5, 3.5), (3.1, 2.8))
    assert ed.spec.bodies[6].position == pytest.approx((3.0, 3.0))


def test_rotate_keeps_joint_closed(ed):
    ed.selection = [("body", 5)]
    assert ed.rotate_selection(90) is None
    a, b = ed.spec.bodies[4], ed.spec.bodies[5]
    assert a.angle == pytest.approx(math.pi / 2) and b.angle == pytest.approx(math.pi / 2)
    joint = ed.spec.joints[0]
    from server.editor.geometry import to_world
    assert to_world(a, joint.anchor_a) == pytest.approx(to_world(b, joint.anchor_b))
    ed.key("r", shift=True)
    ed.key("r", shift=True)
    ed.key("r", shift=True)
    ed.key("r", shift=True)
    ed.key("r", shift=True)
    ed.key("r", shift=True)
    assert ed.spec.bodies[4].angle == pytest.approx(0.0, abs=1e-9)


def test_scale_selection(ed):
    ed.selection = [("body", 6)]
    ed.scale_selection(2.0)
    assert ed.spec.bodies[6].radius == pytest.approx(0.6)
    ed.selection = [("body", 4)]
    ed.scale_selection(0.5)
    joint = ed.spec.joints[0]
    assert joint.anchor_a == pytest.approx((0.225, 0.0))
    assert ed.spec.bodies[5].radius == pytest.approx(0.15)
    from server.editor.geometry import to_world
    assert to_world(ed.spec.bodies[4], joint.anchor_a) == pytest.approx(to_world(ed.spec.bodies[5], joint.anchor_b))
    assert ed.scale_selection(0.0) is not None


def test_delete_body_removes_its_joints_and_thrusters_and_reindexes(ed):
    ed.selection = [("body", 4)]
    ed.key("Delete")
    assert len(ed.spec.bodies) == 6 and ed.spec.joints == [] and ed.spec.thrusters == []
    ed.undo()
    ed.selection = [("body", 5)]
    ed.delete_selection()
    assert ed.spec.joints == [] and len(ed.spec.thrusters) == 1 and ed.spec.thrusters[0].body == 4
    assert ed.spec.bodies[5].position == pytest.approx((3.5, 3.5))  # the lone circle moved down an index
    build(ed.spec, ed.size)


def test_delete_joint_only(ed):
    ed.selection = [("joint", 0)]
    ed.delete_selection()
    assert ed.spec.joints == [] and len(ed.spec.bodies) == 7 and ed.selection == []


def test_copy_paste_keeps_internal_joints_and_offsets(ed):
    ed.box_select(0.9, 0.9, 2.4, 1.5)
    ed.key("c", ctrl=True)
    ed.key("v", ctrl=True)
    assert len(ed.spec.bodies) == 9 and len(ed.spec.joints) == 2 and len(ed.spec.thrusters) == 2
    new = ed.spec.joints[1]
    assert (new.a, new.b) == (7, 8)
    assert ed.spec.bodies[7].position[0] == pytest.approx(ed.spec.bodies[4].position[0] + 0.25)
    assert set(ed.selection) >= {("body", 7), ("body", 8), ("joint", 1)}
    message = ed.paste()
    assert message == 'no thruster left: 2 of 2 used in size l; "Move to size xl" in the panel makes room'


def test_duplicate_single_body(ed):
    ed.selection = [("body", 6)]
    ed.key("d", ctrl=True)
    assert len(ed.spec.bodies) == 8 and ed.selection == [("body", 7)]
    assert ed.spec.bodies[7].radius == ed.spec.bodies[6].radius


def test_nothing_selected_messages(ed):
    ed.selection = []
    assert ed.delete_selection() == "nothing selected"
    assert ed.rotate_selection(15) is not None
    assert ed.paste() is not None


def test_selection_overlay(ed):
    ed.selection = [("body", 6), ("joint", 0), ("thruster", 0)]
    kinds = [shape["kind"] for shape in ed.overlay().selection]
    assert kinds == ["circle", "point", "arrow"]
    ed.key("Escape")
    assert ed.selection == [] and ed.overlay().selection == []


def test_moving_a_body_pinned_to_a_wall_keeps_the_joint_closed(ed):
    from server.editor.geometry import to_world
    ed.set_tool("revolute")
    ed.set_tool("circle")
    drag(ed, (2.5, 0.5), (2.5, 0.8))
    ed.set_tool("revolute")
    ed.click(2.5, 0.35)
    ed.set_tool("select")
    ed.selection = [("body", 7)]
    drag(ed, (2.5, 0.6), (3.0, 1.6))
    joint = ed.spec.joints[-1]
    assert ed.spec.bodies[0].position == (2.5, -4.8)  # the floor stays
    assert to_world(ed.spec.bodies[0], joint.anchor_a) == pytest.approx(to_world(ed.spec.bodies[7], joint.anchor_b))
    ed.rotate_selection(45)
    ed.scale_selection(1.5)
    joint = ed.spec.joints[-1]
    assert to_world(ed.spec.bodies[0], joint.anchor_a) == pytest.approx(to_world(ed.spec.bodies[7], joint.anchor_b))
    assert joint.ref_angle == pytest.approx(ed.spec.bodies[7].angle - ed.spec.bodies[0].angle)


def test_alt_drag_rotates_and_ctrl_drag_resizes(ed):
    ed.selection = [("body", 6)]
    centre = ed.spec.bodies[6].position
    drag(ed, (3.7, 3.5), (3.5, 3.72), alt=True)  # a quarter turn about the circle's centre
    assert ed.spec.bodies[6].angle == pytest.approx(math.pi / 2, abs=1e-6)
    assert ed.spec.bodies[6].position == pytest.approx(centre)
    steps = len(ed.history.undo_stack)
    drag(ed, (3.7, 3.5), (3.9, 3.5), ctrl=True)  # twice as far from the centre: twice the size
    assert ed.spec.bodies[6].radius == pytest.approx(0.6)
    assert len(ed.history.undo_stack) == steps + 1
    ed.undo()
    assert ed.spec.bodies[6].radius == pytest.approx(0.3)
