"""Every numeric field of a level has a documented range, checked in one place (kinetix.ranges, from formats.build)
for every way a level comes in: the loader, `kinetix validate`, the editor and the gallery API (issue 26 §1)."""

from __future__ import annotations

import copy
import json
import re
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kinetix.formats import build, describe
from kinetix.level import LevelError, LevelParams, empty_level
from kinetix.levels import load_level
from kinetix.ranges import RANGES

ROOT = Path(__file__).resolve().parents[2]


def _document():
    """Our format with every kind of numeric field: env, gravity, two polygons, a circle, a joint, a thruster."""
    return {
        "format_version": 1,
        "gravity": [0.0, -9.81],
        "env": {"max_timesteps": 256, "frame_skip": 2, "dense_reward_scale": 0.1,
                "physics": {"dt": 1 / 60, "base_motor_speed": 6.0, "base_motor_power": 900.0,
                            "base_thruster_power": 10.0}},
        "bodies": [
            {"shape": "polygon", "position": [2.5, 0.2], "vertices": [[-2, -0.2], [2, -0.2], [2, 0.2], [-2, 0.2]],
             "fixed": True},
            {"shape": "circle", "position": [1.0, 1.0], "radius": 0.25, "velocity": [0.5, 0.0],
             "angular_velocity": 1.0, "density": 2.0, "friction": 0.5, "restitution": 0.3, "angle": 0.1},
            {"shape": "polygon", "position": [2.0, 1.0], "vertices": [[-0.3, -0.3], [0.3, -0.3], [0.3, 0.3]]},
        ],
        "joints": [{"a": 1, "b": 2, "anchor_a": [0.0, 0.0], "anchor_b": [-0.5, 0.0], "ref_angle": 0.0,
                    "motor": {"speed": 1.0, "power": 1.0}, "limits": [-1.0, 1.0]}],
        "thrusters": [{"body": 2, "anchor": [0.0, 0.0], "angle": 0.0, "power": 1.0}],
    }


# RANGES key -> (path of a value in _document(), component index for vectors or None). Every key must be here.
WHERE = {
    "env.max_timesteps": (("env", "max_timesteps"), None),
    "env.frame_skip": (("env", "frame_skip"), None),
    "env.dense_reward_scale": (("env", "dense_reward_scale"), None),
    "env.physics.dt": (("env", "physics", "dt"), None),
    "env.physics.base_motor_speed": (("env", "physics", "base_motor_speed"), None),
    "env.physics.base_motor_power": (("env", "physics", "base_motor_power"), None),
    "env.physics.base_thruster_power": (("env", "physics", "base_thruster_power"), None),
    "gravity": (("gravity",), 1),
    "body.position": (("bodies", 1, "position"), 0),
    "body.angle": (("bodies", 1, "angle"), None),
    "body.vertices": (("bodies", 2, "vertices", 1), 0),
    "body.radius": (("bodies", 1, "radius"), None),
    "body.density": (("bodies", 1, "density"), None),
    "body.friction": (("bodies", 1, "friction"), None),
    "body.restitution": (("bodies", 1, "restitution"), None),
    "body.velocity": (("bodies", 1, "velocity"), 1),
    "body.angular_velocity": (("bodies", 1, "angular_velocity"), None),
    "joint.anchor_a": (("joints", 0, "anchor_a"), 0),
    "joint.anchor_b": (("joints", 0, "anchor_b"), 1),
    "joint.ref_angle": (("joints", 0, "ref_angle"), None),
    "joint.motor.speed": (("joints", 0, "motor", "speed"), None),
    "joint.motor.power": (("joints", 0, "motor", "power"), None),
    "joint.limits": (("joints", 0, "limits"), 1),
    "thruster.anchor": (("thrusters", 0, "anchor"), 1),
    "thruster.angle": (("thrusters", 0, "angle"), None),
    "thruster.power": (("thrusters", 0, "power"), None),
}


def _field_text(path, index) -> str:
    """How an error names the field: bodies[1].position[0], env.physics.dt, ..."""
    text = ""
    for part in path:
        text += f"[{part}]" if isinstance(part, int) else f".{part}" if text else part
    return text + (f"[{index}]" if index is not None else "")


def _with(document, path, index, value):
    data = copy.deepcopy(document)
    target = data
    for part in path[:-1]:
        target = target[part]
    if index is None:
        target[path[-1]] = value
    else:
        target[path[-1]][index] = value
    return data


def _outside(key: str) -> list:
    r = RANGES[key]
    if r.integer:
        return [r.high + 1, r.low - 1]
    return [r.high * 2 + 1, r.low - abs(r.low) - 1]


def test_the_table_covers_every_field_of_this_test():
    assert set(WHERE) == set(RANGES)
    load_level(_document())  # the base document is valid


@pytest.mark.parametrize("key", sorted(WHERE))
def test_out_of_range_values_are_refused_naming_the_field(key):
    path, index = WHERE[key]
    for value, low_side in zip(_outside(key), (False, True), strict=True):
        if low_side and key == "joint.limits":
            index = 0  # a lower limit below the range (not an upper limit below the lower one)
        field = _field_text(path, index)
        with pytest.raises(LevelError) as error:
            load_level(_with(_document(), path, index, value))
        shown = str(value) if isinstance(value, int) else f"{value:g}"
        assert str(error.value) == f"{field}: {shown} is out of range {RANGES[key].text()}"


def test_the_issue_26_values_are_refused():
    cases = [((("env", "max_timesteps"), None), 2147483648, "env.max_timesteps: 2147483648 is out of range "
                                                             "[1, 100000]"),
             ((("env", "frame_skip"), None), 1e6, "env.frame_skip: 1000000 is out of range [1, 16]"),
             ((("env", "physics", "dt"), None), 1e6, "env.physics.dt: 1e+06 is out of range [0.001, 0.1]"),
             ((("env", "max_timesteps"), None), 10 ** 400, "env.max_timesteps: 1000000"),  # no OverflowError
             ((("bodies", 1, "density"), None), float("inf"), "bodies[1].density: must be finite")]
    for (path, index), value, message in cases:
        with pytest.raises(LevelError, match=re.escape(message)):
            load_level(_with(_document(), path, index, value))


def test_values_at_the_bounds_are_accepted():
    for key in ("env.max_timesteps", "env.frame_skip", "env.physics.dt", "body.restitution", "body.friction",
                "joint.motor.power", "thruster.power", "body.angle", "joint.ref_angle"):
        path, index = WHERE[key]
        for bound in (RANGES[key].low, RANGES[key].high):
            load_level(_with(_document(), path, index, bound))


def test_kinetix_files_name_their_own_fields(shared_dir):
    data = json.loads((shared_dir / "kinetix-levels" / "s" / "h3_point_the_thruster.json").read_text())
    cases = [(("env_params", "max_timesteps"), 2 ** 31, "env_params.max_timesteps: 2147483648 is out of range"),
             (("static_env_params", "frame_skip"), 100, "static_env_params.frame_skip: 100 is out of range [1, 16]"),
             (("env_params", "dt"), 5.0, "env_params.dt: 5 is out of range"),
             (("env_state", "polygon", 4, "rotation"), 1e5, r"env_state.polygon[4].rotation: 100000 is out of range"),
             (("env_state", "polygon", 4, "density"), 1e5, r"env_state.polygon[4].density: 100000 is out of range"),
             (("env_state", "thruster", 0, "power"), 1e4, r"env_state.thruster[0].power: 10000 is out of range")]
    for path, value, message in cases:
        document = _with(data, path, None, value)
        with pytest.raises(LevelError, match=re.escape(message)):
            load_level(document)


def test_every_shipped_and_published_level_is_within_the_ranges(shared_dir):
    paths = sorted((ROOT / "levels").glob("*.json")) + sorted((shared_dir / "kinetix-levels").glob("*/*.json"))
    assert len(paths) > 60
    for path in paths:
        load_level(path)  # raises LevelError naming the field if any value is out of range


def test_levels_built_in_memory_are_checked_too():
    """The editor and resizing build levels from specs: the same check applies (no format reader involved)."""
    spec = describe(empty_level("s"), LevelParams(max_timesteps=2 ** 31))
    with pytest.raises(LevelError, match=re.escape("env.max_timesteps: 2147483648 is out of range [1, 100000]")):
        build(spec)


def test_the_documented_table_matches_the_code():
    """docs/level-format.md lists every range exactly as kinetix.ranges.RANGES holds it."""
    text = (ROOT / "docs" / "level-format.md").read_text()
    rows = dict(re.findall(r"^\| `([a-z_.]+)` \| (\[[^\]]+\]) \|", text, re.MULTILINE))
    assert rows == {key: r.text() for key, r in RANGES.items()}


def test_kinetix_validate_reports_the_field(tmp_path, capsys):
    import argparse

    from kinetix.validate import run

    path = tmp_path / "huge.json"
    path.write_text(json.dumps(_with(_document(), ("env", "max_timesteps"), None, 2147483648)))
    assert run(argparse.Namespace(files=[str(path)], seed=0, steps=10)) == 1
    assert "env.max_timesteps: 2147483648 is out of range [1, 100000]" in capsys.readouterr().out


@settings(max_examples=150, deadline=None, derandomize=True)
@given(key=st.sampled_from(sorted(WHERE)),
       value=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-(2 ** 70), 2 ** 70)))
def test_no_out_of_range_number_is_ever_accepted(key, value):
    """Any number in any field: the level loads with the value inside its range, or the error names that field."""
    path, index = WHERE[key]
    r = RANGES[key]
    try:
        load_level(_with(_document(), path, index, value))
    except LevelError as error:
        last = max(i for i, part in enumerate(path) if isinstance(part, str))
        assert str(error).startswith(_field_text(path[:last + 1], None)), (key, value, str(error))
        return
    assert r.low <= value <= r.high and (not r.integer or float(value).is_integer()), (key, value)
