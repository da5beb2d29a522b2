"""One play thread for every session: steps each playing session on its schedule, batching those due together.

A thread per playing tab made 8 threads fight over the interpreter lock for the same Python work (drawing,
JAX dispatch, viser messages): measured with 8 tabs, each frame cost about twice its single-tab CPU time and
the tabs got 17-20 frames/s. Here one thread does the Python work in turn, and sessions of the same size class
whose ticks fall together step in one compiled batched call (play.Stepper.step_many: 8 plays of size m in
4.1 ms instead of 10.3 ms one by one).

Schedules sit on a shared grid of the play tick (dt x frame skip, 1/30 s by default) so that sessions started
at different moments still come due together. A key press wakes the thread at once and steps that session
straight away, as before (see Session._plan).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from server.session import Session

log = logging.getLogger(__name__)

IDLE_WAIT_S = 0.5  # how long the thread sleeps when no session has a tick coming (a wake cuts it short)


class PlayScheduler:
    def __init__(self) -> None:
        self._sessions: set[Session] = set()
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stopping = False
        self._thread: threading.Thread | None = None

    def add(self, session: Session) -> None:
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
            except Exception:  # a bug here must not stop every tab's play; it is logged and the loop goes on
                log.exception("play scheduler tick failed")
                next_due = None
            wait = IDLE_WAIT_S if next_due is None else max(0.0, next_due - time.perf_counter())
            if wait > 0:
                self._wake.wait(timeout=wait)

    def _tick(self, sessions: list[Session]) -> float | None:
        """Step and draw the sessions that are due; the time of the earliest next tick, or None if none."""
        now = time.perf_counter()
        steps: dict[object, list] = {}  # stepper -> [(session, plan)]
        frames: list[Session] = []
        next_due: float | None = None
        for session in sessions:
            plan = session._plan(now)
            if plan.kind == "drop":
                with self._lock:
                    self._sessions.discard(session)
            elif plan.kind == "step":
                steps.setdefault(plan.stepper, []).append((session, plan))
            elif plan.kind == "frame":
                frames.append(session)
            if plan.next_tick is not None:
                next_due = plan.next_tick if next_due is None else min(next_due, plan.next_tick)
        for stepper, items in steps.items():
            results = stepper.step_many([p.state for _, p in items], [p.action for _, p in items],
                                        [p.params for _, p in items])
            for (session, plan), (state, result) in zip(items, results, strict=True):
                session._finish_step(plan, state, result)
        for session in frames:
            session._push_ack_frame()
        return next_due
