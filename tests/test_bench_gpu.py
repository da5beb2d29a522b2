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
    code = "import os; from kinetix.bench import gpu; gpu.lower_priority(); print(os.nice(0))"
    worker = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    expected = min(19, os.nice(0) + gpu.BACKGROUND_NICENESS)
    assert int(worker) == expected
    tests = subprocess.run(gpu.in_background([sys.executable, "-c", "import os; print(os.nice(0))"]),
                           capture_output=True, text=True, check=True).stdout
    assert int(tests) == expected


def test_kernels_map_to_the_innermost_stage_under_both_trace_namings():
    hlo = "\n".join([
        '  %loop_add_fusion.14 = f32[8]{0} fusion(%p), kind=kLoop, calls=%fc, metadata={op_name="jit(rollout)/while/'
        'body/env_physics/jax2d_substeps/while/body/add" stack_frame_id=3}',
        '  ROOT %wrapped_compare = pred[8]{0} fusion(%q), metadata={op_name="jit(rollout)/env_goal/lt"}',
        '  %copy.2 = f32[8]{0} copy(%r), metadata={op_name="jit(rollout)/transpose"}',
    ])
    stages = gpu.kernel_stages(hlo)
    assert stages["loop_add_fusion.14"] == stages["loop_add_fusion_14"] == "jax2d_substeps"
    assert stages["wrapped_compare"] == "env_goal" and "copy.2" not in stages


def test_the_gpu_variants_set_xla_flags_and_jax2d_option_overrides():
    from jax2d.compiling import OPTIONS_VARIABLE

    eager = gpu.flag_env("eager")
    assert eager["XLA_FLAGS"].endswith("--xla_gpu_enable_command_buffer=")
    assert json.loads(eager[OPTIONS_VARIABLE]) == {"xla_gpu_enable_command_buffer": None,
                                                   "xla_gpu_command_buffer_scheduling_mode": None}
    assert OPTIONS_VARIABLE not in gpu.flag_env("concurrent") or OPTIONS_VARIABLE in os.environ


def test_a_profile_on_this_machine_counts_kernels_per_stage_of_the_step(tmp_path):
    """The same code as on a GPU: a short engine rollout, profiled, its kernels attributed to the step's stages."""
    job = gpu.Job("engine", "s", 4, 3)
    run, *_ = gpu.compile_job(job, None)
    result = gpu.profile(run, tmp_path, job.steps)
    stages = result["by_stage"]
    assert {"jax2d_narrow_phase", "jax2d_substeps", "jax2d_static_walls"} <= set(stages), stages
    assert all(entry["per_step"] > 0 for name, entry in stages.items() if name.startswith("jax2d_"))


def test_the_general_agents_run_resumes_at_the_batch_asked_for():
    """bench/gpu.sh resumes the run with a GPU's batch (TRAIN_ARGS), and its own total unless --train-steps."""
    cmd = gpu.train_command("kinetix/agents/general/sfl-large", None, "--num-envs 4096 --num-minibatches 32")
    assert cmd[cmd.index("--resume") + 1] == "kinetix/agents/general/sfl-large" and "--steps" not in cmd
    assert cmd[-4:] == ["--num-envs", "4096", "--num-minibatches", "32"]
    assert gpu.train_command("r", 10, "")[-2:] == ["--steps", "10"]
