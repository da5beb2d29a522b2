"""`kinetix bench engine` on a tiny configuration: the shape of its results and JSON lines, the scenes, not timings."""

import argparse
import json
import sys

import numpy as np
import pytest

from kinetix.bench import engine, scenes

SIZES = ("s", "m", "l", "xl")
# Slot counts from the issue; polygons include the 4 static walls.
EXPECTED_COUNTS = {"s": (5, 2, 1, 1), "m": (6, 3, 2, 2), "l": (12, 4, 6, 2), "xl": (64, 16, 24, 8)}


@pytest.mark.parametrize("size", SIZES)
def test_scenes_fill_their_capacity_with_walls_first(size):
    batch = scenes.build_batch(size, 3, seed=1)
    polygons, circles, joints, thrusters = EXPECTED_COUNTS[size]
    assert (batch.num_polygons, batch.num_circles, batch.num_joints, batch.num_thrusters) == EXPECTED_COUNTS[size]
    assert batch.bodies.position.shape == (3, polygons + circles, 2)
    assert np.asarray(batch.bodies.active).all()
    assert np.asarray(batch.joints.active).all()
    assert np.asarray(batch.thrusters.active).all()
    inv_mass = np.asarray(batch.bodies.inv_mass)
    assert (inv_mass[:, : scenes.NUM_STATIC] == 0).all(), "walls must be static"
    assert (inv_mass[:, scenes.NUM_STATIC :] > 0).all(), "every other body must be dynamic"
    # The floor's top face is at FLOOR: its centre sits half its height below.
    floor_half_height = float(np.max(np.asarray(batch.bodies.vertices)[0, 0, :, 1]))
    assert np.allclose(np.asarray(batch.bodies.position)[:, 0, 1] + floor_half_height, scenes.FLOOR)
    # Dynamic bodies start inside the walled world, and some start moving.
    dynamic = np.asarray(batch.bodies.position)[:, scenes.NUM_STATIC :]
    assert (dynamic[..., 0] > 0).all() and (dynamic[..., 0] < scenes.WORLD).all()
    assert (dynamic[..., 1] > scenes.FLOOR).all() and (dynamic[..., 1] < scenes.WORLD).all()
    speeds = np.linalg.norm(np.asarray(batch.bodies.velocity), axis=-1)
    assert (speeds[:, scenes.NUM_STATIC :].max(axis=1) > 0.5).all()


def test_batch_elements_differ_but_walls_do_not():
    batch = scenes.build_batch("m", 4, seed=0)
    position = np.asarray(batch.bodies.position)
    walls, dynamic = position[:, : scenes.NUM_STATIC], position[:, scenes.NUM_STATIC :]
    assert (walls == walls[0]).all()
    for i in range(1, 4):
        assert not np.allclose(dynamic[i], dynamic[0])


def test_tiny_benchmark_results_and_json_lines():
    workloads = engine.builtin_workloads(["s"])
    # cold=False: compilations may come from the persistent cache, so a second test run is quick.
    results = engine.benchmark(workloads, [1, 2], 5, loop_calls=5, cold=False)
    lines = [json.loads(json.dumps(result)) for result in results]
    rollouts, loops, summary = lines[:2], lines[2:3], lines[3:]
    assert len(lines) == 4

    for line, batch in zip(rollouts, [1, 2], strict=True):
        assert {"what", "size", "batch", "steps_per_s", "compile_s"} <= line.keys()
        assert "mode" not in line
        assert (line["what"], line["size"], line["batch"], line["steps"]) == ("engine", "s", batch, 5)
        assert line["steps_per_s"] > 0 and line["compile_s"] > 0
        assert line["finite"] is True
        assert line["runs"] == engine.SHORT_RUNS  # runs this short are repeated and the median reported
    (loop,) = loops
    assert {"what", "size", "batch", "mode", "latency_ms", "compile_s"} <= loop.keys()
    assert (loop["what"], loop["size"], loop["batch"], loop["mode"]) == ("engine", "s", 1, "python_loop")
    assert loop["latency_ms"] > 0 and loop["compile_s"] > 0 and loop["finite"] is True
    assert loop["pytree_latency_ms"] > 0  # the plain pytree step, beside the packed one
    (last,) = summary
    assert last["what"] == "engine" and last["peak_rss_mb"] > 10
    assert "size" not in last


def test_timed_runs_reports_the_median_of_short_runs_and_a_long_first_run_alone(monkeypatch):
    """A short run is a warm-up followed by SHORT_RUNS timed runs, reported by their median;
    a run of REPEAT_BELOW_S or more is timed once."""
    durations = iter([0.0, 0.05, 0.01, 0.03, 0.02, 0.04])
    calls = []

    def run():
        calls.append(1)
        return len(calls)

    clock = {"now": 0.0}

    def perf_counter():  # each run advances the clock by its scripted duration when it ends
        return clock["now"]

    def timed(fn):
        def wrapped():
            result = fn()
            clock["now"] += next(durations)
            return result
        return wrapped

    monkeypatch.setattr(engine.time, "perf_counter", perf_counter)
    seconds, result, runs = engine.timed_runs(timed(run))
    # the median of 0.05, 0.01, 0.03, 0.02, 0.04 (after the 0.0 warm-up)
    assert (seconds, result, runs) == (pytest.approx(0.03), 6, engine.SHORT_RUNS)

    durations = iter([engine.REPEAT_BELOW_S + 1.0])
    calls.clear()
    seconds, result, runs = engine.timed_runs(timed(run))
    assert (seconds, result, runs) == (pytest.approx(engine.REPEAT_BELOW_S + 1.0), 1, 1)


def test_table_rows_name_size_batch_and_mode():
    rollout = {"what": "engine", "size": "m", "batch": 16, "steps": 5, "steps_per_s": 1600.0, "compile_s": 2.5,
               "finite": True}
    row = engine.table_row(rollout)
    assert row.split()[:3] == ["m", "16", "scan"]
    assert "1,600" in row and "10.000" in row  # 16 scenes at 1600 steps/s: 10 ms per batched step
    loop = {"what": "engine", "size": "l", "batch": 1, "mode": "python_loop", "latency_ms": 1.25, "compile_s": 3.0,
            "finite": False}
    assert engine.table_row(loop).split()[:4] == ["l", "1", "python", "loop"]
    assert "NON-FINITE" in engine.table_row(loop)


def test_level_option_fails_clearly_without_the_level_loader(capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "kinetix.levels", None)  # importing it now raises ImportError
    args = argparse.Namespace(level="some_level.json", json=False, sizes=["s"], batches=[1], steps=5)
    assert engine.run(args) == 2
    assert engine.NO_LEVEL_LOADER in capsys.readouterr().err


def test_python_loop_runs_in_a_one_device_one_core_child_when_batches_use_two(monkeypatch):
    """With the batches split over 2 devices, the loop is measured in a child process with 1 device on 1 core."""
    from kinetix.devices import DEVICE_COUNT_FLAG

    monkeypatch.setenv("XLA_FLAGS", f"{DEVICE_COUNT_FLAG}=2")  # the child must not inherit this
    (loop,) = engine.interactive_loops("engine", ["--sizes", "s"])
    assert (loop["what"], loop["size"], loop["mode"]) == ("engine", "s", "python_loop")
    assert loop["devices"] == 1 and loop["cores"] == 1 and loop["latency_ms"] > 0 and loop["finite"] is True


def test_loop_latency_comes_from_the_child_and_compile_time_from_this_process(monkeypatch):
    """run_with_interactive_loops: the one-core child's latencies, this process's compile times, rows reported once."""
    here = {"what": "engine", "size": "l", "batch": 1, "mode": "python_loop", "latency_ms": 0.9,
            "pytree_latency_ms": 1.2, "compile_s": 4.5, "cores": 2, "devices": 2, "finite": True}
    batch = {"what": "engine", "size": "l", "batch": 16, "mode": "scan", "steps_per_s": 1000.0}
    child = {**here, "latency_ms": 0.4, "pytree_latency_ms": 0.6, "compile_s": 8.4, "cores": 1, "devices": 1,
             "finite": False}
    monkeypatch.setattr(engine, "interactive_loops", lambda command, selection: [child])

    def measure(report, loops):
        assert loops is True
        for result in (batch, here):
            report(result)
        return [batch, here]

    reported = []
    merged = engine.run_with_interactive_loops(measure, "engine", ["--sizes", "l"], reported.append)
    loop = merged[1]
    assert merged[0] is batch
    assert (loop["latency_ms"], loop["pytree_latency_ms"], loop["cores"], loop["devices"]) == (0.4, 0.6, 1, 1)
    assert (loop["compile_s"], loop["compile_cores"]) == (4.5, 2)
    assert loop["finite"] is False  # either measurement going non-finite fails the run
    assert reported == [batch, loop]  # the loop row is printed once, merged
