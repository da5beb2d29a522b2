"""One session's failure never stops another (issue 26 §1): the play scheduler ends the failing play with a
visible error, logs it once, and keeps stepping the other tabs at their frame rate."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest
from fake_editor import FakeEditor

from kinetix.formats import BodySpec, describe
from kinetix.level import LevelParams, empty_level
from server.play import steps
from server.play.scheduler import PlayScheduler, StepPlan
from tests.server.conftest import running_app, session_of, wait_until

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

# A valid level can no longer make the step raise (its numbers are range-checked), so the failure is injected:
# the stepper raises for plays whose episode length is this (an in-range value no other test uses), as the
# int32 overflow of issue 26 did for an episode length of 2**31.
POISON_STEPS = 4321
MEASURE_S = 2.0  # frames are counted over this long
MIN_FPS = 25.0  # what the issue asks of the healthy tab (the play tick is 30/s)


def _is_poisoned(params) -> bool:
    return int(np.asarray(params.max_timesteps)) == POISON_STEPS


def _long_play_spec(max_timesteps: int):
    """A ball that falls and rolls, with no goal: the play runs until its time limit (256 steps: 8.5 s)."""
    spec = describe(empty_level("m"), LevelParams(max_timesteps=max_timesteps))
    spec.bodies.append(BodySpec(path="ball", shape="circle", position=(1.0, 3.0), radius=0.25, velocity=(1.0, 0.0)))
    return spec


def _editor(level=None, size="m"):
    return FakeEditor(_long_play_spec(256), size=size)


@pytest.fixture(scope="module")
def app():
    with running_app(warm_sizes=("m",), max_sessions=3, editor_factory=_editor) as app:
        yield app


@pytest.fixture
def poisoned_stepper(monkeypatch):
    """Stepper.step and step_many raise for a poisoned play (step_many for the whole batch, as a compiled batch
    would), and work as before for every other play."""
    real_step, real_many = steps.Stepper.step, steps.Stepper.step_many

    def step(self, state, action, params):
        if _is_poisoned(params):
            raise OverflowError("Python int too large to convert to C int (injected)")
        return real_step(self, state, action, params)

    def step_many(self, states, actions, params):
        if any(_is_poisoned(p) for p in params):
            raise OverflowError("Python int too large to convert to C int (injected, batch)")
        return real_many(self, states, actions, params)

    monkeypatch.setattr(steps.Stepper, "step", step)
    monkeypatch.setattr(steps.Stepper, "step_many", step_many)


def _fps(client, session, seconds: float = MEASURE_S) -> float:
    start, t0 = len(client.frames()), time.monotonic()
    time.sleep(seconds)
    assert session.mode == "play", "the healthy play must still be running to be measured"
    return (len(client.frames()) - start) / (time.monotonic() - t0)


def _notifications(client) -> list[dict]:
    return [m["props"] for m in client.matching(lambda m: m["type"] == "NotificationShowMessage")]


def test_a_failing_play_does_not_slow_the_other_tab(app, make_client, poisoned_stepper, caplog):
    healthy_client, bad_client = make_client(app), make_client(app)
    healthy, _ = session_of(app, healthy_client)
    bad, _ = session_of(app, bad_client)
    bad.editor.spec = _long_play_spec(POISON_STEPS)
    bad.editor.revision += 1

    healthy.play()
    wait_until(lambda: len(healthy_client.frames()) >= 5)  # compiled and running
    baseline = _fps(healthy_client, healthy)

    caplog.set_level(logging.WARNING, logger="server.play.scheduler")
    bad.play()
    wait_until(lambda: bad.mode == "edit", timeout=10)  # ended at its first step
    # The failing tab is told, in its status line (the edit view's message) and in a notification.
    assert "Play stopped" in bad._message and "OverflowError" in bad._message
    wait_until(lambda: any("OverflowError" in n["body"] for n in _notifications(bad_client)), timeout=5)

    # While the bad tab keeps failing (its player presses Play again and again), the healthy one keeps its rate.
    restarts = 0
    start, t0 = len(healthy_client.frames()), time.monotonic()
    while time.monotonic() - t0 < MEASURE_S:
        bad.play()
        restarts += 1
        time.sleep(0.4)  # a player pressing Play again every so often
    during = (len(healthy_client.frames()) - start) / (time.monotonic() - t0)
    wait_until(lambda: bad.mode == "edit", timeout=5)
    print(f"healthy tab: {baseline:.1f} frames/s alone, {during:.1f} beside {restarts} failing plays")
    assert healthy.mode == "play" and healthy._message is None
    # >= 25 fps, or on a CI machine too loaded to play at 30 fps even alone, no worse than 85% of its own rate.
    assert during >= min(MIN_FPS, 0.85 * baseline), (during, baseline)

    failures = [r for r in caplog.records if r.name == "server.play.scheduler"]
    assert restarts >= 4 and len(failures) == 1, [r.getMessage() for r in failures]  # logged once, not per play
    assert failures[0].levelno == logging.ERROR and failures[0].exc_info is not None
    healthy.stop()


class _FakeSession:
    """What the scheduler calls: a plan per tick, the step's result, and play_failed."""

    def __init__(self, stepper, state, params, ticks):
        self.stepper, self.state, self.params, self.left = stepper, state, params, ticks
        self.done: list[int] = []
        self.failed: list[str] = []
        self.go = threading.Event()  # _run shares one among its sessions and sets it once all are added

    def plan(self, now):
        if not self.go.is_set():
            return StepPlan("wait", next_tick=now + 0.001)
        if self.left == 0 or self.failed:
            return StepPlan("drop")
        self.left -= 1
        return StepPlan("step", next_tick=now, stepper=self.stepper, state=self.state, params=self.params,
                        action=np.zeros(6, np.int32), play_id=1)

    def finish_step(self, plan, state, result):
        self.done.append(result.timestep)
        self.state = state

    def play_failed(self, error, play_id=None):
        self.failed.append(f"{type(error).__name__}: {error}")


class _FakeStepper:
    """Batches fail if any play in them is poisoned; single steps fail only for the poisoned play."""

    def __init__(self):
        self.batches: list[int] = []

    def step(self, state, action, params):
        if params == "poison":
            raise ValueError("bad play")
        return state + 1, steps.StepResult(0.0, False, False, False, False, state + 1)

    def step_many(self, states, actions, params):
        self.batches.append(len(states))
        if "poison" in params:
            raise ValueError("bad batch")
        return [self.step(s, a, p) for s, a, p in zip(states, actions, params, strict=True)]


def _run(sessions, timeout=10.0):
    scheduler = PlayScheduler()
    try:
        go = threading.Event()  # every session waits until all are added, so they start in the same tick
        for session in sessions:
            session.go = go
            scheduler.add(session)
        go.set()
        deadline = time.monotonic() + timeout
        while scheduler.playing() and time.monotonic() < deadline:
            time.sleep(0.005)
    finally:
        scheduler.close()


def test_a_failing_batch_is_retried_play_by_play_and_only_the_culprit_ends(caplog):
    stepper = _FakeStepper()
    good = [_FakeSession(stepper, 0, "ok", ticks=5) for _ in range(2)]
    bad = _FakeSession(stepper, 0, "poison", ticks=5)
    caplog.set_level(logging.WARNING, logger="server.play.scheduler")
    _run([good[0], bad, good[1]])
    assert [s.done for s in good] == [[1, 2, 3, 4, 5]] * 2  # every tick stepped, the failing one included
    assert bad.done == [] and bad.failed == ["ValueError: bad play"]
    assert stepper.batches[0] == 3  # the three were batched together before the culprit was found
    records = [r for r in caplog.records if r.name == "server.play.scheduler"]
    assert len(records) == 1 and "stepping" in records[0].getMessage()


def test_errors_that_recur_are_logged_with_a_traceback_once(caplog):
    scheduler = PlayScheduler()
    caplog.set_level(logging.WARNING, logger="server.play.scheduler")
    for _ in range(50):
        try:
            raise RuntimeError("same bug")
        except RuntimeError as error:
            scheduler._log_once("play scheduler tick failed", error)
    records = [r for r in caplog.records if r.name == "server.play.scheduler"]
    assert len(records) == 1 and records[0].exc_info is not None


def test_a_session_whose_plan_raises_is_ended_and_the_others_go_on():
    stepper = _FakeStepper()
    good = _FakeSession(stepper, 0, "ok", ticks=3)
    broken = _FakeSession(stepper, 0, "ok", ticks=3)

    def plan(now):
        if broken.failed:
            return StepPlan("drop")
        raise KeyError("plan")

    broken.plan = plan
    _run([broken, good])
    assert good.done == [1, 2, 3] and broken.failed == ["KeyError: 'plan'"]


def test_a_play_whose_frame_cannot_be_drawn_ends_with_a_message(app, make_client, monkeypatch, caplog):
    client = make_client(app)
    session, _ = session_of(app, client)
    real_render = type(session).render

    def render(self):
        if self is session and self.mode == "play":
            raise ZeroDivisionError("cannot draw (injected)")
        return real_render(self)

    monkeypatch.setattr(type(session), "render", render)
    caplog.set_level(logging.WARNING, logger="server.play.scheduler")
    session.play()
    wait_until(lambda: session.mode == "edit", timeout=10)
    assert "ZeroDivisionError: cannot draw" in session._message
    assert len([r for r in caplog.records if r.name == "server.play.scheduler"]) == 1
