"""The `kinetix` command line: help output, argument parsing and unavailable commands."""

import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from kinetix import cli


def run(*command: str) -> subprocess.CompletedProcess:
    return subprocess.run(command, capture_output=True, text=True, timeout=60)


def test_module_help_lists_top_level_commands():
    result = run(sys.executable, "-m", "kinetix.cli", "--help")
    assert result.returncode == 0, result.stderr
    top_level = {command.path[0] for command in cli.COMMANDS}
    assert top_level >= {"bench", "serve"}
    for name in top_level:
        assert name in result.stdout


def test_console_script_bench_help_lists_engine():
    script = Path(sysconfig.get_path("scripts")) / "kinetix"
    assert script.exists(), "console script missing: install the project with `pip install -e .[dev]`"
    result = run(str(script), "bench", "--help")
    assert result.returncode == 0, result.stderr
    assert "engine" in result.stdout


def test_help_does_not_import_jax():
    probe = (
        "import sys\n"
        "from kinetix.cli import main\n"
        "try:\n"
        "    main(['bench', 'engine', '--help'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "print('jax' in sys.modules)\n"
    )
    result = run(sys.executable, "-c", probe)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().endswith("False")


def test_bench_engine_arguments_are_parsed_into_lists():
    args = cli.build_parser().parse_args(["bench", "engine", "--sizes", "s,l", "--batches", "1,64", "--steps", "5"])
    assert args.command.path == ("bench", "engine")
    assert args.sizes == ["s", "l"]
    assert args.batches == [1, 64]
    assert args.steps == 5
    assert args.json is False


@pytest.mark.parametrize("bad", [["--sizes", "s,xxl"], ["--batches", "0"], ["--batches", "two"], ["--steps", "-1"]])
def test_bench_engine_rejects_bad_values(bad, capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.build_parser().parse_args(["bench", "engine", *bad])
    assert exit_info.value.code == 2
    assert f"argument {bad[0]}" in capsys.readouterr().err


def test_group_without_subcommand_prints_help_and_fails(capsys):
    assert cli.main(["bench"]) == 2
    assert "engine" in capsys.readouterr().err


def test_missing_command_module_exits_2_with_message(monkeypatch, capsys):
    ghost = cli.Command(("ghost",), "a command with no module", "kinetix.no_such_module:run", uses_jax=False)
    monkeypatch.setattr(cli, "COMMANDS", [*cli.COMMANDS, ghost])
    assert cli.main(["ghost"]) == 2
    assert "kinetix ghost is not available yet" in capsys.readouterr().err


def test_missing_dependency_inside_a_module_is_not_hidden(tmp_path, monkeypatch):
    # The command's module exists but one of its imports does not: that is a real error, not "not available".
    (tmp_path / "kinetix_probe_bad_import.py").write_text("import kinetix_no_such_dependency\n")
    monkeypatch.syspath_prepend(tmp_path)
    with pytest.raises(ModuleNotFoundError) as error_info:
        cli._load("kinetix_probe_bad_import:run")
    assert error_info.value.name == "kinetix_no_such_dependency"
