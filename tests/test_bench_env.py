"""`kinetix bench env` on a tiny configuration: the shape of its results, the JSON lines and bad input, not timings."""

import argparse
import json

from kinetix.bench import env as bench_env
from kinetix.levels import load_level


def test_default_levels_are_the_reference_files_or_project_stand_ins(shared_dir):
    paths = bench_env.default_level_paths(["s", "m", "l"])
    assert [p.relative_to(shared_dir / "kinetix-levels").as_posix() for p in paths] == [
        "s/h2_one_wheel_car.json", "m/h5_angry_birds.json", "l/h4_cartpole.json"]
    assert [load_level(p).size.name for p in paths] == ["s", "m", "l"]


def test_project_stand_ins_have_the_size_they_stand_in_for():
    for size, name in bench_env.PROJECT_LEVELS.items():
        assert load_level(bench_env.REPO_DIR / "levels" / name).size.name == size


def test_the_env_is_stepped_with_the_solver_its_level_allows():
    """The walls solver (as the server and `kinetix train` pick it) for a level with static walls, the plain one for
    a level with a moving body in polygon slots 0-3, which the walls solver would let through the walls."""
    import dataclasses

    import numpy as np

    from jax2d import SolverConfig
    from kinetix.level import WALLS_SOLVER

    walled = load_level(bench_env.REPO_DIR / "levels" / bench_env.PROJECT_LEVELS["s"])
    env, _ = bench_env._make_env(walled)
    assert env.config.solver == WALLS_SOLVER
    bodies = walled.level.sim.bodies
    moving_floor = dataclasses.replace(bodies, inv_mass=np.asarray(bodies.inv_mass).copy())
    moving_floor.inv_mass[0] = 1.0
    sim = dataclasses.replace(walled.level.sim, bodies=moving_floor)
    unwalled = dataclasses.replace(walled, level=dataclasses.replace(walled.level, sim=sim))
    env, _ = bench_env._make_env(unwalled)
    assert env.config.solver == SolverConfig()


def test_tiny_benchmark_results_and_json_lines():
    level = load_level(bench_env.REPO_DIR / "levels" / bench_env.PROJECT_LEVELS["s"])
    # cold=False: compilations may come from the persistent cache, so a second test run is quick.
    results = bench_env.benchmark([("unicycle", level)], [1, 3], 300, loop_calls=5, pixel_resolutions=(32,),
                                  cold=False)
    lines = [json.loads(json.dumps(result)) for result in results]
    assert len(lines) == 5
    rollouts, (loop, pixels, summary) = lines[:2], lines[2:]
    for line, batch in zip(rollouts, [1, 3], strict=True):
        assert (line["what"], line["size"], line["level"], line["batch"], line["steps"]) == (
            "env", "s", "unicycle", batch, 300)
        assert line["steps_per_s"] > 0 and line["compile_s"] > 0 and line["finite"] is True
        assert line["runs"] >= 1
        # 300 steps exceed the 256-step time limit, so auto-reset ran in every environment at least once.
        assert line["episodes_ended"] >= batch
    assert (loop["mode"], loop["batch"], loop["calls"]) == ("python_loop", 1, 5)
    assert loop["latency_ms"] > 0 and loop["step_compile_s"] > 0 and loop["reset_compile_s"] > 0
    assert loop["pytree_latency_ms"] > 0 and loop["compact_compile_s"] > 0
    assert (pixels["mode"], pixels["resolution"]) == ("pixels", 32)
    assert pixels["ms_per_frame"] > 0 and pixels["ms_per_frame_batched"] > 0
    assert summary["what"] == "env" and summary["peak_rss_mb"] > 10
    for result in results:
        assert bench_env.table_row(result)  # every kind of result has a readable row


def test_bad_level_file_is_a_clear_error(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    args = argparse.Namespace(level=str(bad), json=True, sizes=["s"], batches=[1], steps=5)
    assert bench_env.run(args) == 2
    assert "cannot load level" in capsys.readouterr().err
