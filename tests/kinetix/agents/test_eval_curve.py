"""A run's levels/ learning curve: points merge by steps and protocol, bad input is refused, and a real
evaluation of a checkpoint lands at its step count."""

import json

import jax
import pytest

from kinetix.agents import checkpoint, eval_curve
from kinetix.agents.ppo import TrainConfig, make_network
from kinetix.env import EnvConfig, make_env
from kinetix.level import empty_level


def _results(tmp_path, name, rates):
    path = tmp_path / name
    path.write_text("".join(json.dumps({"level": f"levels/{level}.json", "solve_rate": rate, "mean_return": 2 * rate})
                            + "\n" for level, rate in rates.items()))
    return path


def _checkpoint(path, steps):
    path.mkdir(parents=True)
    (path / "config.json").write_text(json.dumps({"info": {"steps": steps}}))
    return path


def test_points_merge_by_steps_and_protocol_and_redraw_the_png(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    early = _checkpoint(tmp_path / "early", 1000.0)
    late = _checkpoint(tmp_path / "late", 5000.0)
    for ck, rates in ((late, {"a": 0.5, "b": 0.25}), (early, {"a": 0.0, "b": 0.5}), (late, {"a": 1.0, "b": 0.0})):
        assert eval_curve.main([str(run), "--checkpoint", str(ck), "--results",
                                str(_results(tmp_path, "r.jsonl", rates))]) == 0
    eval_curve.main([str(run), "--checkpoint", str(early), "--attempts", "20",
                     "--results", str(_results(tmp_path, "r20.jsonl", {"a": 1.0}))])
    points = json.loads((run / eval_curve.CURVE_JSON).read_text())
    hundred = [p for p in points if p["attempts"] == 100]
    assert [p["env_steps"] for p in hundred] == [1000, 5000]  # sorted; the second 5000 replaced the first
    assert hundred[1]["solve_rate"] == 0.5 and hundred[1]["levels"] == {"a": 1.0, "b": 0.0}
    assert hundred[0]["mean_return"] == 0.5
    assert [p["env_steps"] for p in points if p["attempts"] == 20] == [1000]  # another protocol, kept apart
    assert (run / eval_curve.CURVE_PNG).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_input_is_refused_and_nothing_is_written(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    no_steps = tmp_path / "no-steps"
    no_steps.mkdir()
    (no_steps / "config.json").write_text("{}")
    good = _checkpoint(tmp_path / "good", 10.0)
    broken = tmp_path / "broken.jsonl"
    broken.write_text('{"level": "x", "solve_rate": 1.0}\n')  # no mean_return
    empty = tmp_path / "empty.jsonl"
    empty.write_text("\n")
    results = _results(tmp_path, "r.jsonl", {"a": 1.0})
    assert eval_curve.main([str(run), "--checkpoint", str(no_steps), "--results", str(results)]) == 2
    assert "no info.steps" in capsys.readouterr().err
    assert eval_curve.main([str(run), "--checkpoint", str(good), "--results", str(broken)]) == 2
    assert "not `kinetix eval --json` output" in capsys.readouterr().err
    assert eval_curve.main([str(run), "--checkpoint", str(good), "--results", str(empty)]) == 2
    assert "no results" in capsys.readouterr().err
    assert list(run.iterdir()) == []


def test_a_checkpoint_is_evaluated_at_its_steps(tmp_path):
    env = make_env(EnvConfig("s"), empty_level("s"))
    config = TrainConfig(width=16, hidden=32)
    obs, _ = env.reset(jax.random.key(0))
    params = make_network(config, "multi_discrete").init(jax.random.key(1), jax.tree.map(lambda x: x[None], obs))
    run = tmp_path / "run"
    checkpoint.save(run / "checkpoint", params["params"], config, env.config, {"steps": 4096.0})
    assert eval_curve.main([str(run), "--level", "levels/car_right.json", "--attempts", "2"]) == 0
    [p] = json.loads((run / eval_curve.CURVE_JSON).read_text())
    assert p["env_steps"] == 4096 and p["attempts"] == 2 and p["level_set"] == "levels/car_right.json"
    assert list(p["levels"]) == ["car_right"] and 0.0 <= p["solve_rate"] <= 1.0


@pytest.mark.parametrize("bad", ["levels/does-not-exist.json"])
def test_a_missing_level_set_is_a_clear_error(tmp_path, bad, capsys):
    run = tmp_path / "run"
    _checkpoint(run / "checkpoint", 1.0)
    assert eval_curve.main([str(run), "--level", bad]) == 2
    assert "does-not-exist" in capsys.readouterr().err
    assert not (run / eval_curve.CURVE_JSON).exists()
