"""Properties, global settings, undo/redo, snapping and the overlay of the editor model."""

import math

import pytest

from server.editor import Editor
from tests.server.editor.scenes import drag, hinged_editor


@pytest.fixture
def ed() -> Editor:
    """Body 4 a rectangle, body 5 a circle hinged to it, a thruster on body 4."""
    return hinged_editor()


@pytest.mark.parametrize(("field", "value", "expected", "shown"), [
    ("role", "green", 1, "green"),
    ("role", 3, 3, "red"),
    ("fixed", True, True, True),
    ("density", 2.5, 2.5, 2.5),
    ("friction", 0.3, 0.3, 0.3),
    ("restitution", 0.7, 0.7, 0.7),
    ("collision_mode", "everything", 2, 2),
    ("collision_mode", 0, 0, 0),
])
def test_body_properties(ed, field, value, expected, shown):
    ed.selection = [("body", 4), ("body", 5)]
    assert ed.set_properties(**{field: value}) is None
    assert getattr(ed.spec.bodies[4], field) == expected and getattr(ed.spec.bodies[5], field) == expected
    assert ed.properties()["bodies"][0][field] == shown
    ed.undo()
    assert getattr(ed.spec.bodies[4], field) != expected


@pytest.mark.parametrize(("field", "value", "check"), [
    ("joint_type", "fixed", lambda j: j.fixed),
    ("motor_on", True, lambda j: j.motor_on),
    ("motor_speed", -2.0, lambda j: j.motor_speed == -2.0),
    ("motor_power", 3.0, lambda j: j.motor_power == 3.0),
    ("motor_binding", 3, lambda j: j.motor_binding == 3),
    ("motor_auto", True, lambda j: j.motor_auto),
    ("limits_on", True, lambda j: j.limits == pytest.approx((-math.pi / 4, math.pi / 4))),
])
def test_joint_properties(ed, field, value, check):
    ed.selection = [("joint", 0)]
    assert ed.set_properties(**{field: value}) is None
    assert check(ed.spec.joints[0])
    assert ed.properties()["joints"][0][field] == value


def test_joint_limits(ed):
    ed.selection = [("joint", 0)]
    ed.set_properties(limits_on=True, limit_min=-30.0, limit_max=60.0)
    assert ed.spec.joints[0].limits == pytest.approx((math.radians(-30), math.radians(60)))
    assert ed.set_properties(limit_min=90.0) is not None  # above the max: refused
    assert ed.spec.joints[0].limits == pytest.approx((math.radians(-30), math.radians(60)))
    ed.set_properties(limits_on=False)
    assert ed.spec.joints[0].limits is None
    assert ed.level_file().level.sim.joints.limit_on.sum() == 0


def test_thruster_properties(ed):
    ed.selection = [("thruster", 0)]
    ed.set_properties(thruster_power=2.0, thruster_direction=180.0, thruster_binding=1)
    t = ed.spec.thrusters[0]
    assert (t.power, t.binding) == (2.0, 1) and t.angle == pytest.approx(math.pi)
    assert ed.properties()["thrusters"][0]["thruster_direction"] == pytest.approx(-180.0)


def test_bad_property_values_refused(ed):
    ed.selection = [("body", 4)]
    before = ed.spec
    assert "density" in ed.set_properties(density=-1.0)
    assert "restitution" in ed.set_properties(restitution=2.0)
    assert "unknown" in ed.set_properties(colour="red")
    assert "no joint is selected" in ed.set_properties(motor_on=True)
    assert ed.spec is before


def test_gravity_and_size(ed):
    ed.set_gravity(0.0, -3.0)
    assert ed.spec.gravity == (0.0, -3.0)
    assert ed.level_file().level.sim.gravity.tolist() == [0.0, -3.0]
    assert ed.set_size("m") is None and ed.size.name == "m"
    assert ed.level_file().level.sim.bodies.active.shape == (9,)
    ed.set_tool("circle")
    ed.click(3.0, 3.0)
    ed.click(4.0, 3.0)
    message = ed.set_size("s")
    assert "3 circles > 2 allowed in size s" in message and ed.size.name == "m"
    ed.undo()
    ed.undo()
    ed.undo()
    assert ed.size.name == "l"
    assert ed.set_gravity(float("nan"), 0.0) is not None


def test_undo_redo_each_edit_type(ed):
    def state():
        return (repr(ed.spec.bodies), repr(ed.spec.joints), repr(ed.spec.thrusters), ed.spec.gravity, ed.size.name)

    edits = [
        lambda: ed.set_properties(density=3.0),
        lambda: ed.rotate_selection(30.0),
        lambda: ed.scale_selection(1.2),
        lambda: drag(ed, (1.5, 1.2), (2.5, 2.2)),
        lambda: ed.duplicate_selection(),
        lambda: ed.delete_selection(),
        lambda: ed.set_gravity(1.0, -1.0),
        lambda: ed.set_size("m"),
        lambda: ed.new_level("s"),
    ]
    for edit in edits:
        ed.selection = [("body", 4)] if len(ed.spec.bodies) > 4 else []
        before = state()
        assert edit() is None
        after = state()
        assert after != before
        assert ed.undo() and state() == before
        assert ed.redo() and state() == after
        ed.undo()
        ed.redo()
        assert state() == after


def test_redo_dropped_by_new_edit_and_bounded_history(ed):
    ed.selection = [("body", 4)]
    ed.set_properties(density=2.0)
    ed.key("z", ctrl=True)
    assert ed.can_redo
    ed.set_properties(density=3.0)
    assert not ed.can_redo and not ed.redo()
    ed.key("z", ctrl=True)
    ed.key("z", ctrl=True, shift=True)
    assert ed.spec.bodies[4].density == 3.0
    ed.key("z", ctrl=True)
    ed.key("y", ctrl=True)
    assert ed.spec.bodies[4].density == 3.0
    ed.history.limit = 5
    for k in range(10):
        ed.set_properties(density=4.0 + k)
    undone = 0
    while ed.undo():
        undone += 1
    assert undone == 5 and ed.spec.bodies[4].density == 8.0


def test_undo_keeps_selection_valid(ed):
    ed.set_tool("circle")
    ed.click(3.0, 3.0)
    assert ed.selection == [("body", 6)]
    ed.undo()
    assert ed.selection == []


def test_refused_edit_is_not_an_undo_step(ed):
    steps = len(ed.history.undo_stack)
    ed.set_tool("polygon")
    for p in [(3.0, 3.0), (4.0, 3.0), (3.5, 3.2), (4.0, 4.0), (3.0, 4.0)]:
        ed.click(*p)
    ed.key("Enter")
    assert len(ed.history.undo_stack) == steps


def test_snap_to_grid_vertex_centre_and_midpoint(ed):
    ed.snapping = True
    ed.grid = 0.25
    ed.set_tool("circle")
    ed.click(3.13, 3.37)
    assert ed.spec.bodies[-1].position == pytest.approx((3.25, 3.25))
    ed.undo()
    ed.hover(1.03, 1.02)  # near the rectangle's corner
    overlay = ed.overlay()
    assert overlay.snap_point == pytest.approx((1.0, 1.0))
    assert (1.0, 0.0, 1.0, 5.0) in overlay.guides and (0.0, 1.0, 5.0, 1.0) in overlay.guides
    ed.hover(1.52, 1.43)  # near the middle of the top edge
    assert ed.overlay().snap_point == pytest.approx((1.5, 1.4))
    ed.hover(2.02, 1.19)  # the circle's centre (and the rectangle's right edge midpoint)
    assert ed.overlay().snap_point == pytest.approx((2.0, 1.2))
    ed.hover(1.03, 3.33)  # aligned with the left edge only: an x guide, y from the grid
    overlay = ed.overlay()
    assert overlay.snap_point is None and overlay.guides == [(1.0, 0.0, 1.0, 5.0)]
    ed.click(1.03, 3.33)
    assert ed.spec.bodies[-1].position == pytest.approx((1.0, 3.25))


def test_snapping_off(ed):
    ed.snapping = False
    ed.set_tool("circle")
    ed.click(3.13, 3.37)
    assert ed.spec.bodies[-1].position == (3.13, 3.37)
    assert ed.overlay().guides == []


def test_keys_not_consumed(ed):
    assert not ed.key("ArrowLeft")
    assert not ed.key("q", ctrl=True)
    assert not ed.key("Enter")  # no polygon in progress


def test_episode_and_physics_settings_are_edited_validated_and_undone(ed):
    assert ed.set_params(max_timesteps=500, frame_skip=3, dense_reward_scale=0.0) is None
    file = ed.level_file()
    assert (file.params.max_timesteps, file.params.frame_skip, file.params.dense_reward_scale) == (500, 3, 0.0)
    assert ed.properties()["params"]["max_timesteps"] == 500
    assert ed.set_params(dt=1 / 120, base_motor_power=450.0) is None
    assert ed.level_file().params.dt == 1 / 120 and ed.level_file().params.base_motor_power == 450.0
    # Saved and read back in our format.
    assert '"max_timesteps": 500' in ed.export("ours")
    for bad, words in [({"frame_skip": 0}, "frame_skip must be an integer in [1, 16]"),
                       ({"max_timesteps": 2.5}, "max_timesteps must be an integer"),
                       ({"dt": float("nan")}, "dt must be a finite number"),
                       ({"dense_reward_scale": -1.0}, "dense_reward_scale must be in"),
                       ({"gravity_scale": 1.0}, "unknown level setting 'gravity_scale'")]:
        message = ed.set_params(**bad)
        assert message is not None and words in message, (bad, message)
    assert ed.level_file().params.frame_skip == 3  # refused edits change nothing
    ed.undo()
    assert ed.level_file().params.dt == 1 / 60
    ed.undo()
    assert ed.level_file().params.max_timesteps == 256 and ed.level_file().params.frame_skip == 2
