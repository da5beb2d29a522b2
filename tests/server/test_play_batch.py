"""Batched play steps (several tabs of one size class in one compiled call) and the scheduler that batches them."""

from __future__ import annotations

import logging
import time

import jax
import numpy as np
import pytest

from kinetix.levels import load_level
from server.play import steps
from server.play.scheduler import PlayScheduler
from tests.server.conftest import LEVELS

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


@pytest.fixture(scope="module")
def stepper_and_levels():
    # Two different levels of one size class (m) share one stepper. One batch size (4) keeps this to one
    # compile and makes every batch here padded (2 or 3 plays) or split (9 plays).
    files = [load_level(LEVELS / "car_right.json"), load_level(LEVELS / "thruster_maze.json")]
    assert files[0].size.name == files[1].size.name == "m"
    stepper = steps.stepper_for(files[0])
    assert steps.stepper_for(files[1]) is stepper
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(steps, "BATCH_BUCKETS", (4,))
        patch.setattr(steps, "MIN_BATCH", 2)
        stepper._compile_batched(4)  # what the background compile does, here in the foreground
        assert 4 in stepper._batched
        yield stepper, files
    assert steps.wait_for_compiles(timeout=120)


def _assert_close(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x, np.float64), np.asarray(y, np.float64), rtol=1e-4, atol=1e-4)


def test_a_batched_step_matches_single_steps_for_different_levels(stepper_and_levels):
    stepper, files = stepper_and_levels
    starts = [stepper.start(f) for f in files]
    states, params = [s for s, _ in starts], [p for _, p in starts]
    actions = [steps.action_from_keys({"ArrowRight"}), steps.action_from_keys({"ArrowUp", "Digit1"})]
    for _ in range(10):
        batched = stepper.step_many(states, actions, params)
        single = [stepper.step(s, a, p) for s, a, p in zip(states, actions, params, strict=True)]
        for (bs, br), (ss, sr) in zip(batched, single, strict=True):
            assert (br.terminated, br.truncated, br.solved, br.failed, br.timestep) == (
                sr.terminated, sr.truncated, sr.solved, sr.failed, sr.timestep)
            _assert_close(bs, ss)
        states = [s for s, _ in batched]
    # The two levels really differ, so a batch that mixed them up would fail above.
    positions = [np.asarray(s.level.sim.bodies.position) for s in states]
    assert positions[0].shape == positions[1].shape and not np.allclose(positions[0], positions[1])


def test_odd_and_oversized_batches_are_padded_and_split(stepper_and_levels, monkeypatch):
    stepper, files = stepper_and_levels
    state, params = stepper.start(files[0])
    action = steps.action_from_keys(set())
    one = stepper.step(state, action, params)
    # 3 plays: one padded call; 9 plays: calls of 4, 4 and a single step. Same results for every play.
    calls = []
    monkeypatch.setattr(stepper, "step", lambda *a: calls.append(1) or steps.Stepper.step(stepper, *a))
    for n in (3, 9):
        results = stepper.step_many([state] * n, [action] * n, [params] * n)
        assert len(results) == n
        for s, r in results:
            assert r == one[1]
            _assert_close(s, one[0])
    assert len(calls) == 1  # only the 9th play stepped on its own


class _FakeSession:
    """Just what the scheduler calls: a plan per tick and the step's result."""

    def __init__(self, stepper, state, params, ticks):
        self.stepper, self.state, self.params, self.left = stepper, state, params, ticks
        self.done = []

    def plan(self, now):
        from server.play.scheduler import StepPlan

        if self.left == 0:
            return StepPlan("drop")
        self.left -= 1
        return StepPlan("step", next_tick=now, stepper=self.stepper, state=self.state, params=self.params,
                        action=np.zeros(6, np.int32))

    def finish_step(self, plan, state, result):
        self.done.append(result.timestep)
        self.state = state


def _play_three_ticks_each(stepper, files) -> list[_FakeSession]:
    """A scheduler playing one fake session per level for 3 ticks, run until all are done (30 s at most)."""
    sessions = [_FakeSession(stepper, *stepper.start(f), ticks=3) for f in files]
    scheduler = PlayScheduler()
    try:
        for session in sessions:
            scheduler.add(session)
        deadline = time.monotonic() + 30
        while scheduler.playing() and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        scheduler.close()
    return sessions


def test_the_scheduler_steps_sessions_due_together_in_one_batched_call(stepper_and_levels, monkeypatch):
    stepper, files = stepper_and_levels
    calls = []
    real = stepper.step_many
    monkeypatch.setattr(stepper, "step_many", lambda *a: calls.append(len(a[0])) or real(*a))
    sessions = _play_three_ticks_each(stepper, files)
    assert [s.done for s in sessions] == [[1, 2, 3], [1, 2, 3]]
    assert 2 in calls and sum(calls) == 6  # due together, both stepped in one call


def test_a_broken_batched_step_falls_back_to_single_steps_and_is_logged_once(stepper_and_levels, monkeypatch,
                                                                               caplog):
    # A fault in the batched path itself (every play steps fine alone) must neither stop the plays nor go unseen.
    stepper, files = stepper_and_levels

    def broken(*args):
        raise RuntimeError("injected: the batched path is broken")

    monkeypatch.setattr(stepper, "step_many", broken)
    caplog.set_level(logging.WARNING, logger="server.play.scheduler")
    sessions = _play_three_ticks_each(stepper, files)
    assert [s.done for s in sessions] == [[1, 2, 3], [1, 2, 3]]
    errors = [r for r in caplog.records if r.name == "server.play.scheduler" and r.levelno == logging.ERROR]
    assert len(errors) == 1 and "batched step failed" in errors[0].getMessage(), [r.getMessage() for r in errors]
