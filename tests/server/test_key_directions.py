"""One rule for the arrow keys on every level: Right turns a binding's wheel clockwise, so a car rolls right.

The rule lives in the key -> action mapping (server.play.steps.action_from_keys with
kinetix.bindings.clockwise_values of the level), not in the level files: our levels hold their wheels as joint body
a, the public Kinetix levels as body b, and the motor drives d(angle_b - angle_a)/dt, so the same key needs opposite
binding values on the two.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from kinetix.bindings import _joint_wheel_is_a, clockwise_values
from kinetix.levels import load_level
from server.agents.play import overlay_rows
from server.play import draw
from server.play.steps import action_from_keys, stepper_for

LEVELS = Path(__file__).resolve().parents[2] / "levels"
OUR_VEHICLES = ["car_right", "car_ramp", "car_jump", "hamster_ball", "unicycle"]
PUBLIC_VEHICLES = ["m/h2_car_right", "m/h1_car_left", "l/h3_car_right", "l/h6_lorry", "l/car_launch",
                   "s/h2_one_wheel_car"]
STEPS = 40  # agent steps a key is held: 1.3 s of play


def _drift(level_file, held: set[str]) -> float:
    """Mean x displacement of the moving bodies after holding these keys for STEPS agent steps."""
    stepper = stepper_for(level_file)
    state, params = stepper.start(level_file)
    start = np.asarray(state.level.sim.bodies.position)[:, 0]
    action = action_from_keys(held, clockwise_values(level_file.level))
    for _ in range(STEPS):
        state, result = stepper.step(state, action, params)
        if result.terminated:
            break
    bodies = state.level.sim.bodies
    moving = np.asarray(bodies.active) & (np.asarray(bodies.inv_mass) > 0)
    return float((np.asarray(bodies.position)[:, 0] - start)[moving].mean())


def _check_rolls_right(level_file) -> None:
    right, left = _drift(level_file, {"ArrowRight"}), _drift(level_file, {"ArrowLeft"})
    assert right > 0.1 and right - left > 0.3, f"Right moved it {right:+.2f} m, Left {left:+.2f} m"


@pytest.mark.parametrize("name", OUR_VEHICLES)
def test_right_rolls_our_vehicles_right(name):
    _check_rolls_right(load_level(LEVELS / f"{name}.json"))


@pytest.mark.parametrize("name", PUBLIC_VEHICLES)
def test_right_rolls_imported_public_vehicles_right(name, shared_dir):
    _check_rolls_right(load_level(shared_dir / "kinetix-levels" / f"{name}.json"))


def _car_right(**joint_changes) -> dict:
    doc = json.loads((LEVELS / "car_right.json").read_text())
    for joint in doc["joints"]:
        for key, value in joint_changes.items():
            if key == "speed":
                joint["motor"]["speed"] = value
            else:
                joint[key] = value
    return doc


def test_clockwise_value_follows_which_body_is_the_wheel_and_the_motor_speed_sign():
    assert list(clockwise_values(load_level(_car_right()).level)) == [1, -1, -1, -1]  # wheels are body a
    assert clockwise_values(load_level(_car_right(speed=-1.0)).level)[0] == -1  # a reversed motor flips it
    swapped = _car_right()
    for joint in swapped["joints"]:
        joint["a"], joint["b"] = joint["b"], joint["a"]
        joint["anchor_a"], joint["anchor_b"] = joint["anchor_b"], joint["anchor_a"]
    assert clockwise_values(load_level(swapped).level)[0] == -1  # the wheel is body b, as in public levels
    # The keys follow: Right drives value 1 (+1) on car right, 2 (-1) on the swapped car; Left the opposite.
    assert action_from_keys({"ArrowRight"}, clockwise_values(load_level(_car_right()).level))[0] == 1
    assert action_from_keys({"ArrowLeft"}, clockwise_values(load_level(_car_right()).level))[0] == 2
    assert action_from_keys({"ArrowRight"}, clockwise_values(load_level(swapped).level))[0] == 2
    assert action_from_keys({"ArrowLeft", "ArrowRight"}, np.ones(4))[0] == 0  # both held cancel


def test_the_wheel_rule_in_order():
    free, circle, poly = (False, False), (True, False), (False, False)
    # 1. the body that moves when the other is fixed
    assert _joint_wheel_is_a((False, True), poly, (0.5, 0.0), (1.0, 0.0)) is True
    assert _joint_wheel_is_a((True, False), circle, (0.0, 0.5), (0.0, 1.0)) is False
    # 2. else the circle
    assert _joint_wheel_is_a(free, circle, (0.3, 0.0), (1.0, 1.0)) is True
    assert _joint_wheel_is_a(free, (False, True), (0.0, 0.3), (1.0, 1.0)) is False
    # 3. else the body held nearer its centre
    assert _joint_wheel_is_a(free, poly, (0.1, 0.4), (1.0, 1.0)) is True
    assert _joint_wheel_is_a(free, poly, (0.4, 0.1), (1.0, 1.0)) is False
    # 4. else the heavier body (smaller inverse mass), else a
    assert _joint_wheel_is_a(free, (True, True), (0.0, 0.0), (2.0, 0.5)) is False
    assert _joint_wheel_is_a(free, (True, True), (0.0, 0.0), (1.0, 1.0)) is True


def test_bindings_without_a_keyboard_motor_keep_the_default():
    values = clockwise_values(load_level(LEVELS / "thrust_hop.json").level)  # thrusters only
    assert list(values) == [-1, -1, -1, -1]
    assert action_from_keys({"ArrowRight"}, values)[0] == action_from_keys({"ArrowRight"})[0] == 2


def test_legend_names_keys_by_their_effect():
    assert draw.legend_text({0}, set()) == ["→ motor 0 clockwise  ← anticlockwise"]
    assert draw.legend_text({1, 3}, {1}) == ["↓ motor 1 clockwise  ↑ anticlockwise",
                                             "D motor 3 clockwise  A anticlockwise", "2 thruster 1 fires"]
    scene = draw.scene_of(load_level(LEVELS / "car_right.json").level)
    assert draw.used_bindings(scene) == ({0}, set())


def test_agent_overlay_lists_only_the_levels_own_bindings():
    action = np.array([1, 2, 1, 2, 1, 1], np.int32)
    car = draw.scene_of(load_level(LEVELS / "car_right.json").level)
    texts = [text for text, _ in overlay_rows(action, 0.5, "agent", car)]
    assert texts == ["agent", "motor 0: +", "value +0.500"]
    hop = draw.scene_of(load_level(LEVELS / "thrust_hop.json").level)
    motors, thrusters = draw.used_bindings(hop)
    rows = [text for text, _ in overlay_rows(action, 0.5, "agent", hop)]
    assert rows[1:-1] == [f"thruster {b}: on" for b in sorted(thrusters)] and not motors
