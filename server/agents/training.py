"""Training on a level from the browser: a small pool of worker PROCESSES ("spawn") running train_agent.

    pool = TrainingPool(max_running=1, max_queued=8, per_client=1, per_client_waiting=1)
    job = pool.submit(level_path, out_dir, steps=100_000, on_update=show, on_done=attach, client="author:ab12")
    pool.position(job)      # 0 while running, 1.. while queued
    pool.cancel(job)

This pool is one process's own queue (the default: one `kinetix serve` with SQLite). Several processes on one
PostgreSQL gallery share one queue instead: server.agents.shared_pool.SharedTrainingPool has this interface over the
database's table (server.agents.queue), with the same limits, messages and turns (`check_limits`, `pick_next` and
`projected_order` below serve both).

Why processes: a training run keeps a core busy for minutes and holds the interpreter lock in its Python
parts; in a thread it would starve the play loop. "spawn" (not fork) because JAX must not be forked once it has
initialised (the server has). Workers run niced, so play stays responsive on a small machine.

Who may run what (docs/agents.md, "Training belongs to someone"): every job has a `client` (the tab's author
identity, else the tab). At most `per_client` runs of one client run at once and at most `per_client_waiting`
of them wait; at most `max_queued` runs wait in all. A submit beyond a limit raises TrainingRefused with a
message for the user. When a worker is free the next run is chosen round-robin across clients (the client
served longest ago first, then the oldest of its runs), not first-come-first-served across all requests, so
one client with many runs cannot hold the queue.

Each running job has a supervisor thread that reads the
worker's messages ("progress" dicts, then "done" or "error"), calls `on_update(job)` after each batch of
progress and `on_done(job)` once at the end (state "done", "failed" or "cancelled"), then starts the next
queued job. Cancelling a running job terminates its process at once (nothing of a cancelled run is kept; the
first jitted chunk can take a minute to compile, and `should_stop` is only polled between chunks).
"""

from __future__ import annotations

import collections
import dataclasses
import itertools
import logging
import multiprocessing
import os
import queue as queue_module
import shutil
import threading
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger(__name__)

WORKER_NICE = 5  # training yields the CPU to the play loop
POLL_S = 0.2  # how often a supervisor checks its worker when no message comes
SETTLE_S = 40.0  # close() waits this long for a supervisor (it joins its worker for up to 30 s, then kills it)
DEFAULT_MAX_QUEUED = 8  # runs waiting in all (beyond that a submit is refused: "the queue is full")
DEFAULT_PER_CLIENT = 1  # runs of one client running at once
DEFAULT_PER_CLIENT_WAITING = 1  # runs of one client waiting at once
SERVED_MEMORY = 1024  # clients whose last start the round-robin remembers (the oldest are forgotten first)


class TrainingRefused(ValueError):
    """A run was not queued: a per-client limit or the global queue cap. The message is for the user."""


def train_worker(level_path: str, out_dir: str, steps: int, messages, options: dict) -> None:
    """The worker process: train_agent on the level, reporting progress; runs in a fresh ("spawn") interpreter."""
    try:
        os.nice(WORKER_NICE)
    except OSError:
        pass
    try:
        import dataclasses as dc

        from kinetix.devices import request_cpu_devices

        request_cpu_devices()  # before JAX starts here: the env batch over every core, as `kinetix train` (niced)
        from kinetix.agents.ppo import TrainConfig
        from kinetix.agents.train import train_agent

        config = dc.replace(TrainConfig(), **options.get("config", {}))
        summary = train_agent(level_path, out_dir, steps=steps, config=config, seed=int(options.get("seed", 0)),
                              init=options.get("init"), progress=lambda m: messages.put(("progress", m)))
        last = summary["metrics"][-1] if summary["metrics"] else {}
        messages.put(("done", {"steps": summary["steps"], "solve_rate": last.get("solve_rate"),
                               "mean_return": last.get("mean_return")}))
    except BaseException as error:  # everything goes back to the server as a message, with its type
        messages.put(("error", f"{type(error).__name__}: {error}"))


@dataclasses.dataclass(eq=False)
class TrainingJob:
    id: int
    level_path: Path
    out_dir: Path
    steps: int
    options: dict
    on_update: Callable[[TrainingJob], None] | None = None
    on_done: Callable[[TrainingJob], None] | None = None
    client: str = ""  # who asked for it (per-client limits, round-robin); "" = a client of its own
    state: str = "queued"  # "queued" | "running" | "done" | "failed" | "cancelled"
    progress: list[dict] = dataclasses.field(default_factory=list)
    result: dict | None = None  # the worker's "done" summary: steps, solve_rate, mean_return
    error: str | None = None
    process: object = None
    settled: threading.Event = dataclasses.field(default_factory=threading.Event)  # set once on_done has run
    _cancel: threading.Event = dataclasses.field(default_factory=threading.Event)

    @property
    def finished(self) -> bool:
        return self.state in ("done", "failed", "cancelled")

    def notify(self) -> None:
        """Tell the caller of a change (on_update); its errors are logged, never raised into the pool."""
        if self.on_update is not None:
            try:
                self.on_update(self)
            except Exception:
                log.exception("training progress callback failed")

    def settle(self) -> None:
        """The job ended (its state set): on_done, then `settled`."""
        try:
            if self.on_done is not None:
                self.on_done(self)
        except Exception:
            log.exception("training completion callback failed")
        finally:
            self.settled.set()

    @property
    def fraction(self) -> float:
        """How far the run is, 0..1 (env steps over planned steps)."""
        if self.state == "done":
            return 1.0
        if not self.progress:
            return 0.0
        last = self.progress[-1]
        return min(1.0, float(last["env_steps"]) / max(float(last.get("total_steps") or self.steps), 1.0))


class PoolSettings:
    """What both pools (this one and server.agents.shared_pool's) are given: workers at once, the worker function,
    the queue's limits; checked once here."""

    least_running = 1  # the fewest workers a pool may have

    def __init__(self, max_running: int = 1, worker: Callable = train_worker, context: str = "spawn", *,
                 max_queued: int = DEFAULT_MAX_QUEUED, per_client: int = DEFAULT_PER_CLIENT,
                 per_client_waiting: int = DEFAULT_PER_CLIENT_WAITING):
        if max_running < self.least_running:
            raise ValueError(f"at least one training run must be allowed, got {max_running}" if self.least_running
                             else f"training runs at once cannot be negative, got {max_running}")
        if per_client < 1:
            raise ValueError(f"at least one training run per client must be allowed, got {per_client}")
        if max_queued < 0 or per_client_waiting < 0:
            raise ValueError(f"queue limits cannot be negative, got {max_queued} and {per_client_waiting}")
        self.max_running = max_running
        self.max_queued = max_queued
        self.per_client = per_client
        self.per_client_waiting = per_client_waiting
        self.worker = worker
        self._mp = multiprocessing.get_context(context)


class TrainingPool(PoolSettings):
    def __init__(self, max_running: int = 1, worker: Callable = train_worker, context: str = "spawn", **limits):
        super().__init__(max_running, worker, context, **limits)
        self._lock = threading.Lock()
        self._queued: list[TrainingJob] = []
        self._running: list[TrainingJob] = []
        self._ids = itertools.count(1)
        self._starts = itertools.count(1)
        self._served: collections.OrderedDict[str, int] = collections.OrderedDict()  # client -> its last start
        self._closed = False

    def submit(self, level_path: str | os.PathLike, out_dir: str | os.PathLike, *, steps: int,
               options: dict | None = None, on_update: Callable[[TrainingJob], None] | None = None,
               on_done: Callable[[TrainingJob], None] | None = None, client: str | None = None) -> TrainingJob:
        """Queue a run for `client` (None: a client of its own); it starts now if a worker is free and the client
        runs fewer than `per_client`. Raises TrainingRefused beyond a per-client limit or the queue cap."""
        if steps < 1:
            raise ValueError(f"steps must be positive, got {steps}")
        job_id = next(self._ids)
        job = TrainingJob(job_id, Path(level_path), Path(out_dir), int(steps), dict(options or {}),
                          on_update, on_done, client=client or f"job:{job_id}")
        with self._lock:
            if self._closed:
                raise RuntimeError("the training pool is shut down")
            self._check_limits(job.client)
            self._queued.append(job)
        self._start_next()
        return job

    def _check_limits(self, client: str) -> None:
        """Refuse a new run of `client` that could not start now and has no room to wait (lock held)."""
        running = sum(1 for job in self._running if job.client == client)
        waiting = sum(1 for job in self._queued if job.client == client)
        check_limits(running, waiting, len(self._running), len(self._queued), workers=self.max_running,
                     per_client=self.per_client, per_client_waiting=self.per_client_waiting,
                     max_queued=self.max_queued)

    def _pick(self, queued: list[TrainingJob], served: dict[str, int],
              running: list[TrainingJob] | None = None) -> TrainingJob | None:
        return pick_next(queued, served, self.per_client, running)

    def _projected(self) -> list[TrainingJob]:
        """The queued jobs in the order they would start if every run started at once (lock held)."""
        return projected_order(self._queued, self._served, self.per_client)

    def workers(self) -> int:
        """How many runs may run at once (the tab says so while a run waits)."""
        return self.max_running

    def position(self, job: TrainingJob) -> int:
        """0 while running (or finished), else the job's expected place in the queue (1 = next to start)."""
        with self._lock:
            return self._projected().index(job) + 1 if job in self._queued else 0

    def waits_for_own_run(self, job: TrainingJob) -> bool:
        """True while a queued job waits because its client already runs `per_client` runs."""
        with self._lock:
            return job in self._queued and \
                sum(1 for other in self._running if other.client == job.client) >= self.per_client

    def jobs(self) -> list[TrainingJob]:
        with self._lock:
            return self._running + self._queued

    def cancel(self, job: TrainingJob) -> None:
        """Stop a run: a queued one never starts, a running one's process is terminated."""
        with self._lock:
            if job in self._queued:
                self._queued.remove(job)
                job.state = "cancelled"
                queued = True
            else:
                queued = False
                job._cancel.set()
                process = job.process
        if queued:
            self._finish(job)
            self._notify_queued()
            return
        if process is not None and process.is_alive():
            process.terminate()

    def close(self) -> None:
        """Cancel everything and wait for the workers to exit (server shutdown)."""
        with self._lock:
            self._closed = True
            jobs = self._running + self._queued
        for job in jobs:
            self.cancel(job)
        for job in jobs:
            # A job turns "running" before its process starts (_start_next starts it outside the lock), so a
            # cancel can come first; its supervisor then terminates and joins the process, and settles the job.
            job.settled.wait(timeout=SETTLE_S)
            if job.process is not None:
                job.process.join(timeout=10)

    # ------------------------------------------------------------------ internals

    def _start_next(self) -> None:
        while True:
            with self._lock:
                if self._closed or not self._queued or len(self._running) >= self.max_running:
                    return
                job = self._pick(self._queued, self._served, self._running)
                if job is None:  # every waiting client is at its per-client cap
                    return
                self._queued.remove(job)
                self._running.append(job)
                job.state = "running"
                self._served.pop(job.client, None)
                self._served[job.client] = next(self._starts)
                while len(self._served) > SERVED_MEMORY:  # forget the client served longest ago (it sorts first
                    self._served.popitem(last=False)  # anyway: never-served counts as 0)
            job.out_dir.mkdir(parents=True, exist_ok=True)
            messages = self._mp.Queue()
            job.process = self._mp.Process(target=self.worker, name=f"kinetix-train-{job.id}", daemon=True,
                                           args=(str(job.level_path), str(job.out_dir), job.steps, messages,
                                                 job.options))
            try:
                job.process.start()
            except Exception as error:
                log.exception("could not start a training worker")
                job.state, job.error = "failed", f"could not start the worker: {error}"
                with self._lock:
                    self._running.remove(job)
                self._finish(job)
                continue
            threading.Thread(target=self._supervise, args=(job, messages), name=f"kinetix-train-{job.id}",
                             daemon=True).start()
            self._notify(job)
            self._notify_queued()

    def _notify_queued(self) -> None:
        """The queued jobs moved up: tell them their new positions."""
        with self._lock:
            queued = list(self._queued)
        for other in queued:
            self._notify(other)

    def _supervise(self, job: TrainingJob, messages) -> None:
        process = job.process
        while True:
            try:
                kind, body = messages.get(timeout=POLL_S)
            except queue_module.Empty:
                if job._cancel.is_set() or not process.is_alive():
                    break
                continue
            except (EOFError, OSError):  # the worker died mid-message
                break
            if kind == "progress":
                job.progress.append(body)
                if messages.empty():  # a chunk's updates arrive together: one GUI update per batch
                    self._notify(job)
            elif kind == "done":
                job.result = body
                break
            elif kind == "error":
                job.error = body
                break
        end_worker(process, terminate=job._cancel.is_set())  # cancelled, maybe before its process existed to terminate
        if job._cancel.is_set():
            job.state = "cancelled"
            shutil.rmtree(job.out_dir, ignore_errors=True)  # a cancelled run keeps nothing
        elif job.result is not None:
            job.state = "done"
        else:
            job.state = "failed"
            job.error = job.error or f"the training worker exited with code {process.exitcode}"
        with self._lock:
            if job in self._running:
                self._running.remove(job)
        self._finish(job)
        self._start_next()

    def _notify(self, job: TrainingJob) -> None:
        job.notify()

    def _finish(self, job: TrainingJob) -> None:
        job.settle()


# ---------------------------------------------------------------- the rules, shared with the database queue
# (server.agents.queue): the same limits, messages and turn order whether the queue is this process's or shared.

def end_worker(process, *, terminate: bool) -> None:
    """Reap a worker process, terminated first when `terminate`: it gets 30 s to exit, then SIGKILL."""
    if terminate and process.is_alive():
        process.terminate()
    process.join(timeout=30)
    if process.is_alive():
        process.kill()
        process.join(timeout=5)


def check_limits(running: int, waiting: int, all_running: int, all_waiting: int, *, workers: int, per_client: int,
                 per_client_waiting: int, max_queued: int) -> None:
    """Refuse (TrainingRefused, a message for the user) a new run of a client that runs `running` and has `waiting`
    waiting, when `all_running` of `workers` run and `all_waiting` wait: unless it could start at once, it needs
    room among its own waiting runs and in the queue."""
    if running < per_client and all_running < workers:
        return  # it starts at once
    if waiting >= per_client_waiting:
        mine = running + waiting
        raise TrainingRefused(
            f"you already have {mine} training run{'s' if mine != 1 else ''} going or waiting (at most "
            f"{per_client} running and {per_client_waiting} waiting per person): cancel one or "
            "wait for it to finish")
    if all_waiting >= max_queued:
        raise TrainingRefused(
            f"the training queue is full ({all_waiting} runs waiting for {workers} "
            f"worker{'s' if workers != 1 else ''}): try again when a run has finished")


def pick_next(queued: list, served: dict[str, int], per_client: int, running: list | None = None):
    """The next queued job (anything with `.client` and `.id`) to start: round-robin across clients (the one served
    longest ago, or never, first; then the oldest job). With `running`, a client already at its per-client cap is
    skipped."""
    busy = collections.Counter(job.client for job in running or ())
    ready = [job for job in queued if busy[job.client] < per_client]
    return min(ready, key=lambda job: (served.get(job.client, 0), job.id), default=None)


def projected_order(queued: list, served: dict[str, int], per_client: int) -> list:
    """The queued jobs in the order they would start if every run started at once."""
    served, rest, order = dict(served), list(queued), []
    start = max(served.values(), default=0)
    while rest:
        job = pick_next(rest, served, per_client)
        rest.remove(job)
        order.append(job)
        start += 1
        served[job.client] = start
    return order
