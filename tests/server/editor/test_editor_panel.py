"""The edit-mode viser panel, driven through its GuiApi handles (assigning a value runs the widget's callbacks,
as a browser update does) on a real headless ViserServer."""

import pytest
import viser
from viser._gui_handles import GuiEvent, UploadedFile

from server.editor import Editor
from server.editor.panel import EditorPanel


def upload(panel: EditorPanel, name: str, content: bytes) -> None:
    """What viser does when a browser finishes an upload: store the file, then run the upload callbacks."""
    handle = panel.upload
    handle._impl.value = UploadedFile(name, content)
    for callback in handle._impl.update_cb:
        callback(GuiEvent(client=None, client_id=None, target=handle))


@pytest.fixture(scope="module")
def server():
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield server
    server.stop()


@pytest.fixture
def setup(server):
    editor = Editor(size="l")
    editor.snapping = False
    changes, downloads = [], []
    panel = EditorPanel(server.gui, editor, lambda: changes.append(editor.revision),
                        lambda name, data: downloads.append((name, data)))
    return panel, editor, changes, downloads


def test_tool_buttons(setup):
    panel, editor, changes, _ = setup
    panel.tools.value = "Circle"
    assert editor.tool == "circle" and changes
    panel.tools.value = "Weld"
    assert editor.tool == "fixed"


def test_property_widgets_follow_selection_and_edit_it(setup):
    panel, editor, changes, _ = setup
    editor.set_tool("circle")
    editor.click(2.0, 2.0)
    panel.refresh()
    assert panel.role.visible and not panel.motor_on.visible and not panel.thruster_power.visible
    assert "1 bodies" in panel.summary.content
    panel.role.value = "blue"
    panel.fixed.value = True
    panel.density.value = 2.0
    panel.friction.value = 0.25
    panel.restitution.value = 0.5
    panel.collision.value = "everything"
    body = editor.spec.bodies[-1]
    assert (body.role, body.fixed, body.density, body.friction, body.restitution, body.collision_mode) == (
        2, True, 2.0, 0.25, 0.5, 2)
    panel.undo_button.value = True
    assert editor.spec.bodies[-1].collision_mode == 1 and not panel.redo_button.disabled
    panel.redo_button.value = True
    assert editor.spec.bodies[-1].collision_mode == 2


def test_joint_and_thruster_widgets(setup):
    panel, editor, _, _ = setup
    editor.set_tool("rectangle")
    editor.click(2.0, 2.0)
    editor.set_tool("circle")
    editor.click(2.2, 2.0)
    editor.set_tool("revolute")
    editor.click(2.1, 2.0)
    panel.refresh()
    assert panel.motor_on.visible and not panel.role.visible
    panel.motor_on.value = True
    panel.motor_speed.value = 2.0
    panel.motor_power.value = 3.0
    panel.motor_binding.value = "3: A / D clockwise"
    panel.motor_auto.value = True
    panel.limits_on.value = True
    panel.limit_min.value = -10.0
    panel.limit_max.value = 20.0
    joint = editor.spec.joints[0]
    assert (joint.motor_on, joint.motor_speed, joint.motor_power, joint.motor_binding) == (True, 2.0, 3.0, 3)
    assert joint.motor_auto
    assert joint.limits == pytest.approx((-0.17453292, 0.34906585))
    panel.joint_type.value = "fixed"
    assert editor.spec.joints[0].fixed and panel.motor_on.disabled
    editor.set_tool("thruster")
    editor.click(1.9, 2.0)
    panel.refresh()
    panel.thruster_power.value = 4.0
    panel.thruster_direction.value = 0.0
    panel.thruster_binding.value = "1: key 2"
    thruster = editor.spec.thrusters[0]
    assert (thruster.power, thruster.angle, thruster.binding) == (4.0, 0.0, 1)


def test_level_settings_limits_and_messages(setup):
    panel, editor, _, _ = setup
    panel.gravity.value = (0.0, -4.0)
    assert editor.spec.gravity == (0.0, -4.0)
    panel.param_widgets["max_timesteps"].value = 400
    panel.param_widgets["dt"].value = 0.01
    assert (editor.spec.params.max_timesteps, editor.spec.params.dt) == (400, 0.01)
    panel.param_widgets["frame_skip"].value = 0  # out of range: refused with a message, the widget shows the level
    assert "frame_skip must be an integer" in panel.message.content
    assert editor.spec.params.frame_skip == 2 and panel.param_widgets["frame_skip"].value == 2
    assert panel.limits_line.content == "**Left:** 8 polygons, 4 circles, 6 joints, 2 thrusters"
    panel.size.value = "s"
    assert editor.size.name == "s"
    assert panel.limits_line.content == "**Left:** 1 polygons, 2 circles, 1 joints, 1 thrusters"
    editor.set_tool("circle")
    editor.click(1.0, 3.0)
    editor.click(2.0, 3.0)
    editor.click(3.0, 3.0)
    panel.refresh()
    assert "no circle left" in panel.message.content
    panel.snapping.value = True
    panel.grid.value = 0.5
    assert editor.snapping and editor.grid == 0.5


def test_new_level_button(setup):
    panel, editor, _, _ = setup
    editor.set_tool("circle")
    editor.click(1.0, 3.0)
    panel.size.value = "m"
    panel.buttons["New level"].value = True
    assert len(editor.spec.bodies) == 4 and editor.size.name == "m"


def test_edit_buttons(setup):
    panel, editor, _, _ = setup
    editor.set_tool("circle")
    editor.click(1.0, 3.0)
    panel.buttons["Duplicate"].value = True
    assert len(editor.spec.bodies) == 6
    panel.buttons["Grow"].value = True
    assert editor.spec.bodies[-1].radius == pytest.approx(0.22)
    panel.buttons["Rotate +15°"].value = True
    assert editor.spec.bodies[-1].angle == pytest.approx(0.2617993877991494)
    panel.buttons["Copy"].value = True
    panel.buttons["Paste"].value = True
    assert len(editor.spec.bodies) == 7
    panel.buttons["Delete"].value = True
    assert len(editor.spec.bodies) == 6
    panel.buttons["Undo"].value = True
    assert len(editor.spec.bodies) == 7


def test_download_and_upload(setup):
    panel, editor, _, downloads = setup
    editor.set_tool("circle")
    editor.click(1.0, 3.0)
    panel.download("ours")
    panel.download("kinetix")
    (name_ours, ours), (name_kinetix, kinetix) = downloads
    assert name_ours == "level.json" and name_kinetix == "level.kinetix.json"
    assert ours.decode() == editor.export("ours")
    upload(panel, "broken.json", b"{")
    assert "not valid JSON" in panel.message.content and len(editor.spec.bodies) == 5
    editor.new_level("l")
    upload(panel, "mine.kinetix.json", kinetix)
    assert len(editor.spec.bodies) == 5 and panel.message.content == ""


def test_kinetix_download_of_a_pentagon_says_what_was_split_in_the_panel(setup):
    panel, editor, _, downloads = setup
    editor.set_tool("polygon")
    for p in [(3.0, 3.0), (4.0, 3.0), (4.5, 3.5), (4.0, 4.0), (3.0, 4.0)]:
        editor.click(*p)
    editor.key("Enter")
    panel.download("kinetix")
    assert downloads and downloads[-1][0] == "level.kinetix.json"
    status = panel.file_status.content
    assert status == ("Downloaded level.kinetix.json: split 1 polygon (5 vertices) into 2 parts welded by 1 fixed "
                      "joint; exported as size l.")
    assert panel.message.content == ""  # nothing on the canvas's message line


def test_a_download_that_cannot_be_written_gives_the_whole_reason_in_the_panel(setup):
    import json

    panel, editor, _, downloads = setup
    level = json.loads(editor.export("ours"))
    level["bodies"][2]["fixed"] = False  # the right wall no longer fixed: not a public Kinetix level
    editor.import_bytes(json.dumps(level).encode())
    panel.download("kinetix")
    assert not downloads
    status = panel.file_status.content
    assert status.startswith("**Cannot download in the Kinetix format:**") and status.endswith("add\\_walls")
    assert panel.message.content == ""


def test_the_panel_offers_the_next_size_when_the_level_is_full(setup):
    panel, editor, _, _ = setup
    panel.size.value = "s"
    editor.set_tool("circle")
    for x in (1.0, 2.0, 3.0):
        editor.click(x, 3.0)
    panel.refresh()
    button = panel.grow_button
    assert button.visible and button.label == "Move to size m"
    button.value = True  # a click
    assert editor.size.name == "m" and editor.limits()["circles"] == (3, 3)
    assert not button.visible and panel.size.value == "m"
