"""One play thread for every session: steps each playing session on its schedule, batching those due together.

A thread per playing tab made 8 threads fight over the interpreter lock for the same Python work (drawing,
JAX dispatch, viser messages): measured with 8 tabs, each frame cost about twice its single-tab CPU time and
the tabs got 17-20 frames/s. Here one thread does the Python work in turn, and sessions of the same size class
whose ticks fall together step in one compiled batched call (play.Stepper.step_many: 8 plays of size m in
4.1 ms instead of 10.3 ms one by one).

Schedules sit on a shared grid of the play tick (dt x frame skip, 1/30 s by default) so that sessions started
at different moments still come due together. A key press wakes the thread at once and steps that session
straight away, as before (see Session.plan).

Isolation: one session's failure never stops another. Everything done for one session (its plan, its step, its
frame) runs under its own try; an exception ends that session's play with a visible message (Playable.play_failed)
and the others go on in the same tick. A batched step that raises is retried one play at a time, so only the
play that fails is ended and the innocent ones keep their frame rate. A failed play ends, so its error is logged
once; the same error again (same place, type and message) is logged without its traceback, at most once a minute.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from typing import Protocol

import numpy as np

log = logging.getLogger(__name__)

IDLE_WAIT_S = 0.5  # how long the thread sleeps when no session has a tick coming (a wake cuts it short)
MAX_LOGGED_ERRORS = 1000  # distinct errors remembered by _log_once
LOG_REPEAT_S = 60.0  # an error seen again is logged (as one line with a count) at most this often


@dataclasses.dataclass
class StepPlan:
    """What the play scheduler should do for a session this tick (Playable.plan)."""

    kind: str  # "step" | "frame" (push a frame acknowledging a key) | "wait" | "drop" (no longer playing)
    next_tick: float | None = None  # when the session is next due (perf_counter seconds), if it plays
    stepper: object = None
    state: object = None
    params: object = None
    action: np.ndarray | None = None
    play_id: int = 0
    ack: bool = False


class Playable(Protocol):
    """What the scheduler needs of a playing session (server.play.session.Session offers it). The scheduler knows
    only this, so it does not import the session (no import cycle) and tests can schedule stand-ins."""

    def plan(self, now: float) -> StepPlan:
        """What to do this tick: step (with the stepper, state, params and action), push a frame, wait or drop."""
        ...

    def finish_step(self, plan: StepPlan, state, result) -> None:
        """Take the stepped state and result: record, draw and push the frame, end the episode if it ended."""
        ...

    def push_ack_frame(self) -> None:
        """Push a frame acknowledging the keys pressed since the last one (a paused or waiting play)."""
        ...

    def play_failed(self, error: BaseException, play_id: int | None = None) -> None:
        """End this play (if `play_id` is still the current one) and say why in the tab."""
        ...


class PlayScheduler:
    def __init__(self) -> None:
        self._sessions: set[Playable] = set()
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._logged: dict[tuple, tuple[float, int]] = {}  # error -> (last logged, repeats since) (see _log_once)

    def add(self, session: Playable) -> None:
        """Schedule this session (it has started playing); wakes the thread."""
        with self._lock:
            if self._stopping:
                return
            self._sessions.add(session)
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="kinetix-play", daemon=True)
                self._thread.start()
        self._wake.set()

    def wake(self) -> None:
        """Look at the sessions now (a key, pause, step or stop happened)."""
        self._wake.set()

    def close(self) -> None:
        with self._lock:
            self._stopping = True
            self._sessions.clear()
            thread = self._thread
        self._wake.set()
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=5.0)

    def playing(self) -> int:
        with self._lock:
            return len(self._sessions)

    def _run(self) -> None:
        while True:
            with self._lock:
                if self._stopping:
                    return
                sessions = list(self._sessions)
            self._wake.clear()
            try:
                next_due = self._tick(sessions)
            except Exception as error:  # a bug outside any one session: logged (once) and the loop goes on
                self._log_once("play scheduler tick failed", error)
                next_due = None
            wait = IDLE_WAIT_S if next_due is None else max(0.0, next_due - time.perf_counter())
            if wait > 0:
                self._wake.wait(timeout=wait)

    def _tick(self, sessions: list[Playable]) -> float | None:
        """Step and draw the sessions that are due; the time of the earliest next tick, or None if none."""
        now = time.perf_counter()
        steps: dict[object, list] = {}  # stepper -> [(session, plan)]
        frames: list[Playable] = []
        next_due: float | None = None
        for session in sessions:
            try:
                plan = session.plan(now)
            except Exception as error:
                self._fail(session, None, "planning its step", error)
                continue
            if plan.kind == "drop":
                self._drop(session)
            elif plan.kind == "step":
                steps.setdefault(plan.stepper, []).append((session, plan))
            elif plan.kind == "frame":
                frames.append(session)
            if plan.next_tick is not None:
                next_due = plan.next_tick if next_due is None else min(next_due, plan.next_tick)
        for stepper, items in steps.items():
            for session, plan, stepped in self._step_group(stepper, items):
                try:
                    session.finish_step(plan, *stepped)
                except Exception as error:
                    self._fail(session, plan, "drawing its step", error)
        for session in frames:
            try:
                session.push_ack_frame()
            except Exception as error:
                self._fail(session, None, "drawing its frame", error)
        return next_due

    def _step_group(self, stepper, items: list) -> list:
        """[(session, plan, (state, result))] for the plays of one stepper that stepped; the failed ones are ended.

        One batched call first; if it raises, each play steps alone, so one bad play cannot take the others down.
        A lone play that fails is stepped alone again too (its state is a value, so that has no side effect): a
        play's failure is then always the single step's error, logged once whether or not it shared a tick.
        """
        try:
            results = stepper.step_many([p.state for _, p in items], [p.action for _, p in items],
                                        [p.params for _, p in items])
            return [(session, plan, result) for (session, plan), result in zip(items, results, strict=True)]
        except Exception as error:
            batch_error = error  # which play failed, and how, is found and reported by stepping each alone below
        stepped = []
        for session, plan in items:
            try:
                stepped.append((session, plan, stepper.step(plan.state, plan.action, plan.params)))
            except Exception as error:
                self._fail(session, plan, "stepping", error)
        if len(stepped) == len(items):  # no play is at fault: the batched path itself is, and must not hide
            self._log_once("a batched step failed where each play stepped alone", batch_error)
        return stepped

    def _drop(self, session: Playable) -> None:
        with self._lock:
            self._sessions.discard(session)

    def _fail(self, session: Playable, plan, doing: str, error: Exception) -> None:
        """End this session's play with a visible error (it then drops out of the schedule by itself)."""
        self._log_once(f"a play failed while {doing}", error)
        try:
            session.play_failed(error, None if plan is None else plan.play_id)
        except Exception as second:  # the session cannot even show the error: stop looking at it
            self._drop(session)
            self._log_once("could not end a failed play", second)

    def _log_once(self, what: str, error: Exception) -> None:
        """The traceback the first time an error is seen; after that a one-line count at most every LOG_REPEAT_S.

        A play that fails is ended, so its error comes once; this also keeps an error that recurs every tick
        (a bug outside any session, or many plays of one bad level) from flooding the log.
        """
        frame = error.__traceback__
        while frame is not None and frame.tb_next is not None:
            frame = frame.tb_next
        where = (frame.tb_frame.f_code.co_filename, frame.tb_lineno) if frame is not None else None
        key = (what, type(error).__name__, str(error)[:200], where)
        now = time.monotonic()
        with self._lock:
            first = key not in self._logged
            if first and len(self._logged) >= MAX_LOGGED_ERRORS:
                self._logged.clear()  # a bound on memory; at worst an old error's traceback is logged again
            last, count = self._logged.get(key, (now - LOG_REPEAT_S, 0))
            due = first or now - last >= LOG_REPEAT_S
            self._logged[key] = (now, 0) if due else (last, count + 1)
        if first:
            log.error("%s", what, exc_info=error)
        elif due:
            log.warning("%s again (%d more times since): %s: %s", what, count + 1, type(error).__name__, error)
