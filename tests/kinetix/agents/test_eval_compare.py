"""eval_compare on hand-written `kinetix eval --json` files: per-set means, churn against the file before (only over
levels both evaluated), and clear errors for files that are not evaluations."""

import json

import pytest

from kinetix.agents.eval_compare import compare, main


def _write(path, rates):
    path.write_text("".join(json.dumps({"level": k, "solve_rate": v, "mean_return": 0.0}) + "\n"
                            for k, v in rates.items()))
    return path


def test_means_per_set_and_churn_against_the_file_before(tmp_path):
    a = _write(tmp_path / "a.jsonl", {"levels/x.json": 1.0, "levels/y.json": 0.0, "generated-s/00": 0.5})
    # x lost 0.75, y gained 0.25: the mean falls by 0.25, the churn is 0.5; z is new and not compared
    b = _write(tmp_path / "b.jsonl", {"levels/x.json": 0.25, "levels/y.json": 0.25, "levels/z.json": 1.0,
                                      "generated-s/00": 0.5})
    first, second = compare([a, b])
    assert first["churn"] == {}
    assert first["sets"]["levels"] == {"levels": 2, "mean": 0.5}
    assert second["sets"]["levels"]["levels"] == 3
    assert second["sets"]["levels"]["mean"] == pytest.approx(1.5 / 3)
    assert second["churn"]["levels"] == {"levels": 2, "churn": pytest.approx(0.5)}
    assert second["churn"]["generated-s"] == {"levels": 1, "churn": 0.0}


def test_the_command_prints_the_table_and_json(tmp_path, capsys):
    a = _write(tmp_path / "a.jsonl", {"levels/x.json": 1.0})
    b = _write(tmp_path / "b.jsonl", {"levels/x.json": 0.4})
    assert main([str(a), str(b)]) == 0
    text = capsys.readouterr().out
    assert "mean solve rate 0.400" in text and "churn 0.600 over 1 levels" in text
    assert main([str(a), str(b), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)[1]["churn"]["levels"]["churn"] == pytest.approx(0.6)


@pytest.mark.parametrize("content, message", [
    ("not json\n", "not `kinetix eval --json` output"),
    ('{"level": "levels/x.json"}\n', "not `kinetix eval --json` output"),
    ("", "no results"),
    ('{"level": "levels/x.json", "solve_rate": 1, "mean_return": 0}\n' * 2, "appears twice"),
])
def test_a_file_that_is_not_an_evaluation_is_refused(tmp_path, capsys, content, message):
    bad = tmp_path / "bad.jsonl"
    bad.write_text(content)
    assert main([str(bad)]) == 2
    assert message in capsys.readouterr().err


def test_a_missing_file_is_refused(tmp_path, capsys):
    assert main([str(tmp_path / "nope.jsonl")]) == 2
    assert "nope.jsonl" in capsys.readouterr().err
