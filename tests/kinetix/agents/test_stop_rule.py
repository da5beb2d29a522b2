"""kinetix train's early stopping: a wall-clock budget and a solve rate held over recent updates."""

import pytest

from kinetix.agents.train import StopRule


def update(solve_rate: float, episodes: int = 4) -> dict:
    return {"solve_rate": solve_rate, "episodes": episodes}


def test_target_needs_a_full_window_at_the_rate():
    rule = StopRule(target_solve_rate=0.9, window=4)
    for rate in (1.0, 1.0, 1.0):
        rule.observe(update(rate))
        assert not rule()  # fewer than `window` updates seen
    rule.observe(update(0.5))
    assert not rule()  # mean 0.875
    for _ in range(3):  # the 0.5 is still inside the window
        rule.observe(update(1.0))
        assert not rule()
    rule.observe(update(1.0))
    assert rule() and "solve rate" in rule.reason


def test_updates_without_finished_episodes_do_not_count():
    rule = StopRule(target_solve_rate=0.5, window=2)
    rule.observe(update(1.0))
    rule.observe(update(0.0, episodes=0))
    rule.observe(update(float("nan")))
    assert not rule()
    rule.observe(update(1.0))
    assert rule()


def test_time_budget(monkeypatch):
    clock = [100.0]
    monkeypatch.setattr("kinetix.agents.train.time.perf_counter", lambda: clock[0])
    rule = StopRule(minutes=2)
    clock[0] += 119
    assert not rule()
    clock[0] += 1
    assert rule() and "2 min" in rule.reason


@pytest.mark.parametrize("kwargs", [{"minutes": 0}, {"minutes": -1}, {"target_solve_rate": 0},
                                    {"target_solve_rate": 1.5}])
def test_bad_limits_are_refused(kwargs):
    with pytest.raises(ValueError, match="--"):
        StopRule(**kwargs)
