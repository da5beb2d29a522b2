"""The compiles a server runs after it answers HTTP: the play step of each size class first, then the batched steps
and the general agent, one after another on one background thread.

Why after: compiling before serving made a warm start (the JAX cache filled) take 16 s to the first HTTP 200, and a
cold one 31 s, while the page itself needs none of it. A tab that opens meanwhile draws its level and says
"preparing the simulation (compiling size m: 2 of 5)"; a play asked for before its size class is ready starts
when it is (Session.play waits for it, see WarmUp.when_ready), it does not fail.

    warm = WarmUp(("s", "m", "l"), batches=True, agent=warm_agent)
    warm.start(then=keep_frame_buffers_resident)
    warm.ready("m"); warm.progress()  # -> "compiling size m: 2 of 5", or None when all is done
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

log = logging.getLogger(__name__)

PREPARING = "preparing the simulation"  # the words a tab shows while its play step compiles


class WarmUp:
    """The ordered compile tasks of a server start, their progress, and who waits for which size class."""

    def __init__(self, sizes: tuple[str, ...], *, batches: bool = True,
                 agent: Callable[[tuple[str, ...]], None] | None = None, frame_skip: int = 2):
        """`agent(sizes)`: compiles an agent for the size classes (server.agents.play.warm_agent), last."""
        self.sizes = tuple(sizes)
        self.frame_skip = frame_skip
        self.tasks: list[tuple[str, str]] = [("size", name) for name in self.sizes]  # (kind, size or "")
        if batches and self.sizes:
            self.tasks.append(("batches", ""))
        self._agent = agent
        if agent is not None and self.sizes:
            self.tasks.append(("agent", ""))
        self._calls: dict[str, Callable[[], object]] = {}  # label -> work added with prepend
        self._done = 0
        self._current: tuple[str, str] | None = None
        self._ready: set[str] = set()
        self._finished = threading.Event()
        self._cancelled = threading.Event()
        self._lock = threading.Lock()
        self._waiting: list[tuple[str | None, Callable[[], None]]] = []  # (size or None for "any news", callback)

    def prepend(self, label: str, work: Callable[[], object]) -> None:
        """Run `work()` before the compiles (e.g. adding the project's levels to a new gallery, which renders a
        thumbnail for each); `label` names it in the progress ("preparing <label>: 1 of 6"). Before start() only."""
        self._calls[label] = work
        self.tasks.insert(0, ("call", label))

    # ------------------------------------------------------------------ what sessions ask

    def ready(self, size: str) -> bool:
        """Whether a play of this size class can start without compiling its step here. A size class that is not
        warmed at start (a custom size) is compiled by its first play, as before."""
        with self._lock:
            return size in self._ready or size not in self.sizes

    def progress(self) -> str | None:
        """e.g. "compiling size m: 2 of 5", "compiling the batched steps: 4 of 5"; None once every task is done."""
        if not self.tasks:
            return None
        with self._lock:
            if self._finished.is_set():
                return None
            task = self._current or self.tasks[min(self._done, len(self.tasks) - 1)]
            return f"{self._label(task)}: {self._done + 1} of {len(self.tasks)}"

    @staticmethod
    def _label(task: tuple[str, str]) -> str:
        kind, size = task
        return {"size": f"compiling size {size}", "batches": "compiling the batched steps",
                "agent": "compiling the agent", "call": f"preparing {size}"}[kind]

    def when_ready(self, size: str, callback: Callable[[], None]) -> bool:
        """Call `callback()` (on the warm-up thread) once `size` is ready; False (and no call) if it is already."""
        with self._lock:
            if size in self._ready or size not in self.sizes:
                return False
            self._waiting.append((size, callback))
            return True

    def on_progress(self, callback: Callable[[], None]) -> None:
        """Call `callback()` after every task (tabs redraw their progress line)."""
        with self._lock:
            self._waiting.append((None, callback))

    def wait(self, timeout: float | None = None, sizes_only: bool = True) -> bool:
        """Block until the play steps (or, with sizes_only=False, every task) are compiled; False on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            with self._lock:
                if self._finished.is_set() or (sizes_only and self._ready >= set(self.sizes)):
                    return True
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return False
            self._finished.wait(timeout=0.05 if left is None else min(0.05, left))

    @property
    def finished(self) -> bool:
        return self._finished.is_set()

    # ------------------------------------------------------------------ the background thread

    def start(self, then: Callable[[], None] | None = None) -> threading.Thread:
        """Run every task in order on a background compile thread (one the server's shutdown waits for), then
        `then()` on that thread."""
        from server.play import steps

        return steps._start_compile(self._run, then)

    def cancel(self) -> None:
        """Skip the tasks not started yet (the server is stopping: only the compile under way is waited for)."""
        self._cancelled.set()

    def _run(self, then: Callable[[], None] | None) -> None:
        for task in self.tasks:
            if self._cancelled.is_set():
                log.info("warm-up: %s skipped (the server is stopping)", self._label(task))
                continue
            with self._lock:
                self._current = task
            self._notify(None)
            t0 = time.perf_counter()
            try:
                self._compile(*task)
                log.info("warm-up: %s done in %.1f s", self._label(task), time.perf_counter() - t0)
            except Exception:  # a failed compile is logged; a play of that size then compiles on first use
                log.exception("warm-up: %s failed", self._label(task))
            with self._lock:
                self._done += 1
                if task[0] == "size":
                    self._ready.add(task[1])
            if task[0] == "size":
                self._notify(task[1], progress=False)  # the next task's start tells the progress
        with self._lock:
            self._current = None
            self._finished.set()
        self._notify(None)
        if then is not None:
            then()

    def _compile(self, kind: str, size: str) -> None:
        from server.play import steps

        if kind == "size":
            steps.warm_up((size,), frame_skip=self.frame_skip)
        elif kind == "call":
            self._calls[size]()
        elif kind == "batches":
            steps.warm_batches((*self.sizes,), frame_skip=self.frame_skip)
        else:
            self._agent(self.sizes)

    def _notify(self, size: str | None, progress: bool = True) -> None:
        """Call the callbacks waiting for `size` (removed after) and, with `progress`, every progress callback."""
        with self._lock:
            due = [cb for s, cb in self._waiting if (s is None and progress) or (size is not None and s == size)]
            self._waiting = [(s, cb) for s, cb in self._waiting if s is None or s != size]
        for callback in due:
            try:
                callback()
            except Exception:  # one tab's trouble does not stop the warm-up of the others
                log.exception("a warm-up callback failed")
