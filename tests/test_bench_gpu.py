"""kinetix.bench.gpu (bench/gpu.sh): the GPU call's plan and its report; the call itself needs a GPU (docs/gpu.md)."""

import json
import os
import subprocess
import sys

from kinetix.bench import gpu


def test_the_plan_covers_the_issue_grid_with_the_goal_batches_first():
    ab, grid, train = gpu.plan(quick=False)
    measured = {(job.what, job.size, job.batch) for job in grid}
    assert measured == {(what, size, batch) for what in ("env", "engine") for size in "sml"
                        for batch in (256, 2048, 16384, 65536)}
    assert len(grid) == len(measured) and all(job.control_flow is None and not job.flags for job in grid)
    # a call cut short still has the goal's points: s and l at 2,048 and 16,384 come first, m last
    assert {(job.size, job.batch) for job in grid[:8]} == {(s, b) for s in "sl" for b in (2048, 16384)}
    assert all(job.size == "m" for job in grid[-8:])
    assert [(job.size, job.batch) for job in train] == [("m", 1024), ("m", 8192)]
    assert {job.control_flow for job in ab} == {"skip", "fixed", None}
    # each XLA-flag variant at env s and env l, beside the grid's env s and l at the same batch
    assert [(job.flags, job.what, job.size, job.batch) for job in ab if job.flags] == [
        (flags, "env", size, gpu.AB_BATCH) for flags in gpu.FLAG_VARIANTS for size in "sl"]
    assert gpu.plan(quick=False, flows=False, train=False)[0] == [job for job in ab if job.flags]
    assert gpu.plan(quick=False, train=False)[2] == []


def test_a_short_call_narrows_the_grid_to_the_sizes_and_batches_asked_for():
    ab, grid, train = gpu.plan(quick=False, flows=False, train=False, flag_variants=False, sizes=("s", "l"),
                               batches=(2048, 16384))
    assert ab == [] and train == []
    assert sorted((job.what, job.size, job.batch) for job in grid) == sorted(
        (what, size, batch) for what in ("env", "engine") for size in "sl" for batch in (2048, 16384))
    assert {job.size for job in gpu.plan(quick=True, sizes=("m",))[1]} == {"m"}


def test_each_scan_is_long_enough_and_the_names_tell_the_variants_apart():
    for batch in (256, 2048, 16384, 65536):
        assert 25_000 <= batch * gpu.rollout_steps(batch) <= 700_000 and gpu.rollout_steps(batch) >= 10
    names = [job.name for job in gpu.plan(quick=False)[0]]
    assert len(set(names)) == len(names)
    assert "env s 2048+concurrent" in names and "env l 2048+concurrent" in names and "env s 2048/fixed" in names


def test_the_table_compares_with_the_reference_only_where_there_is_one():
    results = [
        {"what": "env", "size": "s", "batch": 2048, "control_flow": "default", "steps_per_s": 1_238_000.0,
         "compile_s": 24.1},
        {"what": "env", "size": "m", "batch": 2048, "control_flow": "default", "steps_per_s": 600_000.0,
         "compile_s": None},
        {"what": "error", "job": "engine l 256", "error": "boom"},
        {"what": "train", "size": "m", "num_envs": 1024, "steps_per_second": 86_000.0},
    ]
    lines = gpu.table(json.loads(json.dumps(results))).splitlines()
    assert lines[1].split()[:6] == ["env", "s", "2048", "default", "1,238,000", "2.00"]  # 619k in the reference
    assert lines[2].split()[-1] == "-" and "x ref" in lines[0]
    assert lines[3].split()[:5] == ["train", "m", "1024", "PPO", "86,000"]
    assert len(lines) == 4  # the error is not a row


def test_the_compile_workers_and_tests_run_below_the_training_runs():
    """The training program is the call's longest compile: the grid's workers and the tests yield the CPU to it."""
    niceness = subprocess.run([sys.executable, "-c", "import os; print(os.nice(0))"], capture_output=True, text=True,
                              preexec_fn=gpu.lower_priority, check=True).stdout
    assert int(niceness) == min(19, os.nice(0) + gpu.BACKGROUND_NICENESS)
