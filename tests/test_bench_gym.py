"""`kinetix bench gym` on a tiny configuration: the shape of its results and bad input, not timings."""

import argparse

import pytest

pytest.importorskip("gymnasium", reason="kinetix bench gym needs the gym extra: pip install -e '.[gym]'")

from kinetix.bench import env as bench_env  # noqa: E402
from kinetix.bench import gym as bench_gym  # noqa: E402


def test_tiny_comparison_results_and_rows():
    # The JAX rollout of tests/test_bench_env.py (unicycle, batch 3, 300 steps): from the persistent cache there.
    path = bench_env.REPO_DIR / "levels" / bench_env.PROJECT_LEVELS["s"]
    results = bench_gym.benchmark([path], [3], 300)
    jax_env, gym_env, ratio, summary = results
    assert (jax_env["what"], gym_env["what"], ratio["what"]) == ("env", "gym", "gym_vs_jax")
    for line in (jax_env, gym_env):
        assert (line["size"], line["level"], line["batch"], line["steps"]) == ("s", "unicycle", 3, 300)
        assert line["steps_per_s"] > 0 and line["compile_s"] > 0
    # 300 steps (and the warm-up) exceed the 256-step time limit: every gym environment ended an episode.
    assert gym_env["episodes_ended"] >= 3 and gym_env["repeats"] == bench_gym.REPEATS
    assert ratio["ratio"] == pytest.approx(gym_env["steps_per_s"] / jax_env["steps_per_s"])
    assert summary["peak_rss_mb"] > 10
    for result in results:
        assert bench_gym.table_row(result)


def test_bad_level_file_is_a_clear_error(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    args = argparse.Namespace(level=str(bad), json=True, sizes=["s"], batches=[1], steps=5, observation="entity")
    assert bench_gym.run(args) == 2
    assert "cannot load level" in capsys.readouterr().err
