"""`kinetix validate` and `kinetix convert`: output lines, exit codes, grouping, atomic writes."""

import dataclasses
import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jax2d import scene
from kinetix import cli, validate
from kinetix.level import LevelError, LevelFile, LevelParams, SizeClass, empty_level, make_level
from kinetix.levels import dumps, load_level, save_level

STEPS = 40  # enough to move things; every test uses the same count so the program compiles once
TINY = SizeClass("custom", polygons=4, circles=1, joints=1, thrusters=1)  # the walls and a wheel: quick to compile


def wheel_level(speed: float = 1.0) -> LevelFile:
    """A wheel pinned to the left wall by a motor, with a thruster: every kind of entity, in a tiny size."""
    sim = empty_level(TINY).sim
    sim, wheel = scene.add_circle(sim, (0.3, 1.0), 0.25)
    sim, _ = scene.add_revolute_joint(sim, 1, wheel, (0.0, 1.0), motor_on=True, motor_speed=speed)
    sim, _ = scene.add_thruster(sim, wheel, (0.3, 1.0), angle=0.5, power=2.0)
    return LevelFile(make_level(sim), LevelParams(), TINY, "wheel")


@pytest.fixture
def level_files(tmp_path):
    """The same tiny level in our format and in the Kinetix format, and a malformed file."""
    ours_path, theirs_path, bad_path = tmp_path / "wheel.json", tmp_path / "wheel.kinetix.json", tmp_path / "bad.json"
    save_level(wheel_level(), ours_path)
    save_level(wheel_level(speed=2.0), theirs_path, format="kinetix")
    data = json.loads(ours_path.read_text())
    data["bodies"][4]["radius"] = -1
    bad_path.write_text(json.dumps(data))
    return ours_path, theirs_path, bad_path


def run_cli(capsys, *argv):
    code = cli.main(list(argv))
    out, err = capsys.readouterr()
    return code, out.splitlines(), err


def test_validate_reports_each_file_and_fails_if_any_fails(capsys, level_files):
    ours_path, theirs_path, bad_path = level_files
    code, lines, _ = run_cli(capsys, "validate", "--steps", str(STEPS), str(ours_path), str(bad_path),
                             str(theirs_path))
    assert code == 1
    assert lines == [f"OK  {ours_path}",
                     f"FAIL {bad_path}: bodies[4].radius: must be > 0, got -1.0",
                     f"OK  {theirs_path}"]
    code, lines, err = run_cli(capsys, "validate", "--steps", str(STEPS), str(ours_path), str(theirs_path))
    assert code == 0 and lines == [f"OK  {ours_path}", f"OK  {theirs_path}"] and err == ""


def test_validated_levels_really_move_and_nan_counts_as_failure():
    files = [wheel_level(), wheel_level()]
    b = files[1].level.sim.bodies
    broken_sim = dataclasses.replace(files[1].level.sim, bodies=dataclasses.replace(
        b, angular_velocity=b.angular_velocity.at[4].set(jnp.nan)))
    files[1] = dataclasses.replace(files[1], level=dataclasses.replace(files[1].level, sim=broken_sim))
    levels = validate.stack([f.level for f in files])
    params = validate.stack([f.params.sim_params() for f in files])
    keys = jnp.stack([jax.random.key(0), jax.random.key(1)])
    final, finite = validate.simulate(levels, params, keys, STEPS)
    assert np.asarray(finite).tolist() == [True, False]
    # The motor and thruster acted: the wheel turned and moved from where it started.
    assert abs(float(final.bodies.angle[0, 4])) > 0.01
    assert float(np.linalg.norm(final.bodies.position[0, 4] - files[0].level.sim.bodies.position[4])) > 1e-3


def test_validate_compiles_once_per_capacity_and_keeps_the_input_order(monkeypatch, tmp_path, level_files):
    ours_path, theirs_path, _ = level_files
    larger = tmp_path / "larger.json"
    save_level(wheel_level(), larger, size="m")
    calls = []

    def fake_simulate(levels, params, keys, steps):
        calls.append((levels.capacity, int(keys.shape[0]), steps))
        return None, jnp.ones(keys.shape[0], bool)

    monkeypatch.setattr(validate, "simulate", fake_simulate)
    results = validate.validate([str(ours_path), str(larger), str(theirs_path)], steps=7)
    assert [r.path for r in results] == [str(ours_path), str(larger), str(theirs_path)]
    assert all(r.ok for r in results)
    assert sorted((c.polygons, n, steps) for c, n, steps in calls) == [(4, 2, 7), (6, 1, 7)]


def test_validate_subprocess_exit_status_for_broken_files(tmp_path):
    not_json, missing = tmp_path / "notes.json", tmp_path / "missing.json"
    not_json.write_text("this is not json")
    result = subprocess.run([sys.executable, "-m", "kinetix", "validate", str(not_json), str(missing)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 1, result.stderr
    lines = result.stdout.splitlines()
    assert len(lines) == 2
    assert lines[0].startswith(f"FAIL {not_json}: ") and "is not valid JSON" in lines[0]
    assert lines[1].startswith(f"FAIL {missing}: cannot read")


def test_convert_defaults_to_the_other_format_and_round_trips(capsys, tmp_path, level_files):
    ours_path, _, _ = level_files
    theirs, back = tmp_path / "out.kinetix.json", tmp_path / "back.json"
    code, lines, _ = run_cli(capsys, "convert", str(ours_path), str(theirs))
    assert code == 0 and "kinetix format" in lines[0]
    assert load_level(theirs).format == "kinetix"
    code, _, _ = run_cli(capsys, "convert", str(theirs), str(back))
    assert code == 0
    # Our format -> Kinetix -> ours loses only the name (their files have none; the file name is used).
    original, returned = json.loads(ours_path.read_text()), json.loads(back.read_text())
    assert returned.pop("name") == "out.kinetix" and original.pop("name") == "wheel"
    assert returned == original


def test_convert_resizes_and_leaves_the_output_untouched_on_error(capsys, tmp_path, level_files):
    ours_path, _, bad_path = level_files
    out = tmp_path / "out.json"
    code, _, _ = run_cli(capsys, "convert", str(ours_path), str(out), "--to", "ours", "--size", "l")
    assert code == 0 and load_level(out).size.name == "l"
    before = out.read_text()
    code, _, err = run_cli(capsys, "convert", str(bad_path), str(out), "--to", "ours")
    assert code == 1 and "bodies[4].radius: must be > 0" in err
    sim = scene.remove_body(empty_level("l").sim, 2)  # no right wall: the public format needs its 4 walls
    wallless = tmp_path / "wallless.json"
    wallless.write_text(dumps(LevelFile(make_level(sim))))
    code, _, err = run_cli(capsys, "convert", str(wallless), str(out))
    assert code == 1 and "in polygon slots 0-3" in err
    assert out.read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.json", "out.json", "wallless.json", "wheel.json",
                                                        "wheel.kinetix.json"]


def test_validate_and_convert_are_registered_commands():
    paths = {command.path for command in cli.COMMANDS}
    assert {("validate",), ("convert",)} <= paths
    args = cli.build_parser().parse_args(["convert", "a.json", "b.json", "--to", "kinetix", "--size", "m"])
    assert (args.input, args.output, args.to, args.size) == ("a.json", "b.json", "kinetix", "m")
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["convert", "a.json", "b.json", "--to", "yaml"])
    assert issubclass(LevelError, ValueError)
