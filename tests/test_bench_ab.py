"""`python -m kinetix.bench.ab`: an older commit's packages beside this tree's in one process."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from kinetix.bench import ab

ROOT = Path(__file__).resolve().parents[1]


def test_imports_are_pointed_at_the_renamed_packages():
    source = textwrap.dedent("""\
        import jax2d
        import jax
        from jax2d.state import SimState
        from kinetix import env
        from kinetix.bench.engine import (
            timed_runs,
        )
        import kinetix
            import jax2d
        x = "kinetix.bench.gpu"  # a dotted name in a string or comment stays: kinetix.env
        import jax2dx
        from kinetixfoo import y
        """)
    renamed = ab.rename_imports(source)
    assert renamed.splitlines() == [
        "import jax2d_before as jax2d",
        "import jax",
        "from jax2d_before.state import SimState",
        "from kinetix_before import env",
        "from kinetix_before.bench.engine import (",
        "    timed_runs,",
        ")",
        "import kinetix_before as kinetix",
        "    import jax2d_before as jax2d",
        'x = "kinetix.bench.gpu"  # a dotted name in a string or comment stays: kinetix.env',
        "import jax2dx",
        "from kinetixfoo import y",
    ]


def _git_available() -> bool:
    return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True).returncode == 0


@pytest.mark.skipif(not _git_available(), reason="needs this checkout's git history")
def test_an_exported_tree_imports_only_its_own_packages(tmp_path):
    """The export of HEAD, renamed, imports its bench modules without touching this tree's jax2d or kinetix: the
    renaming covers every import form the tree uses."""
    ab.export_tree("HEAD", tmp_path)
    assert (tmp_path / "jax2d_before" / "step.py").is_file() and not (tmp_path / "jax2d").exists()
    script = textwrap.dedent(f"""\
        import sys
        sys.path.insert(0, {str(tmp_path)!r})
        import kinetix_before.bench.env, kinetix_before.bench.engine, kinetix_before.levels
        leaked = sorted(m for m in sys.modules if m.split(".")[0] in ("jax2d", "kinetix"))
        print(leaked)
        sys.exit(1 if leaked else 0)
        """)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path, env=env)
    assert done.returncode == 0, done.stdout + done.stderr


def test_an_unknown_commit_is_a_clear_error(tmp_path):
    with pytest.raises(SystemExit, match="git archive no-such-commit-xyz failed"):
        ab.export_tree("no-such-commit-xyz", tmp_path)


@pytest.mark.parametrize("text", ["x:16", "s:", "s:0", "s:-1", "s16"])
def test_bad_workloads_are_refused(text):
    with pytest.raises(SystemExit):
        ab.parse_args(["--before", "HEAD", "--engine", text])


def test_xl_is_an_engine_workload_but_not_an_env_one():
    assert ab.parse_args(["--before", "HEAD", "--engine", "xl:16"]).engine == [("xl", 16)]
    with pytest.raises(SystemExit):
        ab.parse_args(["--before", "HEAD", "--env", "xl:16"])


def test_nothing_to_measure_is_refused(capsys):
    with pytest.raises(SystemExit):
        ab.parse_args(["--before", "HEAD"])
    assert "nothing to measure" in capsys.readouterr().err


@pytest.mark.skipif(not _git_available(), reason="needs this checkout's git history")
def test_a_tiny_engine_ab_against_head_runs_both_sides():
    done = subprocess.run(
        [sys.executable, "-m", "kinetix.bench.ab", "--before", "HEAD", "--engine", "s:2", "--rounds", "2",
         "--steps", "2", "--devices", "1", "--json"],
        capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    (result,) = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    assert (result["what"], result["size"], result["batch"], result["rounds"]) == ("engine", "s", 2, 2)
    assert result["before_steps_per_s"] > 0 and result["after_steps_per_s"] > 0
    assert len(result["ratios"]) == 2 and result["ratio_min"] <= result["ratio_median"] <= result["ratio_max"]


def test_the_summary_compares_medians_rounds_and_fastest_runs():
    from kinetix.bench.ab import summary

    # before: 2, 1, 4 s; after: 1, 2, 1 s (10 scenes x 10 steps)
    result = summary("engine", "s", 10, 10, [2.0, 1.0, 4.0], [1.0, 2.0, 1.0])
    assert result["ratios"] == [2.0, 0.5, 4.0]
    assert result["ratio_median"] == 2.0 and (result["ratio_min"], result["ratio_max"]) == (0.5, 4.0)
    assert result["ratio_best"] == 1.0  # fastest 1 s each
    assert result["before_steps_per_s"] == 50.0 and result["after_steps_per_s"] == 100.0
