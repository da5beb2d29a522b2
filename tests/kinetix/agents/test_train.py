"""A short training run on an easy project level beats the random policy (both measured here), and the
train/eval command lines write and print what they promise."""

import json
from pathlib import Path

import pytest

from kinetix.agents.evaluate import evaluate
from kinetix.agents.ppo import TrainConfig
from kinetix.agents.train import train_agent
from kinetix.cli import main
from kinetix.levels import load_level

ROOT = Path(__file__).resolve().parents[3]
# catapult: the arm must wait for the ball to settle, then fling; random actions solve it sometimes (the
# solve rate of random play is measured below, never assumed), a learned policy nearly always.
EASY = ROOT / "levels" / "catapult.json"
SMALL = ROOT / "levels" / "unicycle.json"


@pytest.mark.slow
def test_short_training_beats_random(tmp_path):
    config = TrainConfig(num_envs=32, num_steps=64, updates_per_call=4)
    summary = train_agent(str(EASY), tmp_path / "run", steps=32 * 64 * 16, config=config, seed=0)
    assert len(summary["metrics"]) == 16
    for name in ("checkpoint/config.json", "checkpoint/params.msgpack", "metrics.json", "curve.png"):
        assert (tmp_path / "run" / name).is_file(), name
    levels = [("catapult", load_level(EASY))]
    trained = evaluate(str(tmp_path / "run" / "checkpoint"), levels, attempts=20, seed=1)[0]
    random = evaluate("random", levels, attempts=20, seed=1)[0]
    assert trained["solve_rate"] > random["solve_rate"], (trained, random)


def test_eval_json_shape(capsys):
    assert main(["eval", "--agent", "noop", "--level", str(SMALL), "--attempts", "2", "--json"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1
    row = json.loads(lines[0])
    assert set(row) == {"level", "solve_rate", "mean_return"}
    assert row["level"] == str(SMALL) and 0.0 <= row["solve_rate"] <= 1.0  # noop is checked not to solve it
    assert row["solve_rate"] == 0.0


def test_eval_and_train_reject_bad_input(capsys, tmp_path):
    assert main(["eval", "--agent", "nonsense", "--level", str(SMALL)]) == 2
    assert "unknown agent" in capsys.readouterr().err
    assert main(["eval", "--agent", "noop", "--level", str(tmp_path / "missing.json")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["train", "--level", str(SMALL), "--curriculum", "sfl", "--out", str(tmp_path / "o")]) == 2
    assert "needs random levels" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_sfl_options_reach_the_curriculum_config(capsys):
    from kinetix.agents.train import settings_from_args
    from kinetix.cli import build_parser

    args = build_parser().parse_args(["train", "--level", "random-s", "--curriculum", "sfl", "--sfl-candidates", "64",
                                      "--sfl-attempts", "8", "--buffer-size", "16", "--sfl-refresh-every", "5"])
    config = settings_from_args(args)["curriculum_config"]
    assert (config.candidates, config.attempts, config.buffer_size, config.refresh_every) == (64, 8, 16, 5)
    assert "curriculum_config" not in settings_from_args(build_parser().parse_args(["train", "--level", "random-s"]))
    for bad in ("0", "-2", "two"):
        with pytest.raises(SystemExit):
            build_parser().parse_args(["train", "--level", "random-s", "--sfl-attempts", bad])
        assert "--sfl-attempts" in capsys.readouterr().err


def test_gamma_and_gae_lambda_options(capsys, tmp_path):
    from kinetix.agents.train import settings_from_args
    from kinetix.cli import build_parser

    args = build_parser().parse_args(["train", "--level", str(SMALL), "--gamma", "0.995", "--gae-lambda", "0.9"])
    config = settings_from_args(args)["config"]
    assert (config.gamma, config.gae_lambda) == (0.995, 0.9)
    assert settings_from_args(build_parser().parse_args(["train", "--level", str(SMALL)]))["config"].gamma == 0.99
    for option, bad in (("--gamma", "0"), ("--gamma", "1.5"), ("--gae-lambda", "-0.1"), ("--gae-lambda", "nan")):
        out = tmp_path / f"o{bad}"
        assert main(["train", "--level", str(SMALL), option, bad, "--out", str(out)]) == 2
        name = option[2:].replace("-", "_")
        assert f"{name} must be a number with" in capsys.readouterr().err
        assert not out.exists()
