"""TrainingPool's interface over the shared queue (server.agents.queue): what `kinetix serve --db postgresql://...`
uses, so a tab's run may be trained by any process on the database and still reports to the tab that asked.

    pool = SharedTrainingPool(store, max_running=1, work_dir=data_dir / "agents" / ".work")
    job = pool.submit(level_path, out_dir, steps=4000, client="author:ab12", on_update=show, on_done=attach)
    pool.position(job); pool.cancel(job); pool.close()

Each process plays two parts, through one background thread (`_loop`, every POLL_S):
- **Asker**: `submit` queues a row (the level document travels in it: the worker may be on another host) and keeps a
  TrainingJob mirror of it; the loop reads the states of its own jobs, copies progress, calls `on_update` on every
  change (state, progress, queue position) and, once a job ends, fetches its checkpoint from the row into the job's
  `out_dir/checkpoint` (where TrainingPool's worker would have written it) and calls `on_done`. `cancel` ends a
  queued job at once and flags a running one, wherever it runs.
- **Worker**: while fewer than `max_running` of its runs go, it claims the next job in turn (at submit, when one of
  its runs ends, and on every loop), trains it in a spawned worker process exactly as TrainingPool does (same worker
  function, in `work_dir/job-<id>`), writes progress to the row after every batch of updates, stops a run flagged
  for cancelling, and stores the packed checkpoint (server.gallery.checkpoints, ~0.5 MB) with the result.

Heartbeats and the sweep of dead processes' jobs: every HEARTBEAT_S (server.agents.queue). A clean shutdown
(`close`) cancels the jobs this process asked for (their tabs close with it) and gives the jobs it ran for other
processes back to the queue, where another process starts them afresh.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import queue as queue_module
import secrets
import shutil
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path

from server.agents.queue import HEARTBEAT_S, LEASE_S, Limits, TrainingQueue
from server.agents.training import POLL_S, SETTLE_S, PoolSettings, TrainingJob, end_worker, train_worker
from server.gallery.checkpoints import CheckpointError, pack_checkpoint, unpack_checkpoint

log = logging.getLogger(__name__)

WATCH_S = 0.25  # how often the loop reads its jobs' states and looks for a job to claim
CLAIM_EVERY_S = 1.0  # at most this often a process with a free slot asks the database for work it did not see start
REPORT_EVERY_S = 0.5  # a run's progress is written at most this often (every batch of updates otherwise)


@dataclasses.dataclass(eq=False)
class _Run:
    """A job this process's worker runs (for itself or another process)."""

    job_id: int
    owner: str
    work_dir: Path
    process: object = None
    stop: threading.Event = dataclasses.field(default_factory=threading.Event)  # cancelled: terminate now
    leaving: threading.Event = dataclasses.field(default_factory=threading.Event)  # shutdown: give it back


class SharedTrainingPool(PoolSettings):
    least_running = 0  # 0: this process asks but trains nothing (another process's workers do)

    def __init__(self, store, max_running: int = 1, worker: Callable = train_worker, context: str = "spawn", *,
                 work_dir: str | os.PathLike, lease_s: float = LEASE_S, heartbeat_s: float = HEARTBEAT_S,
                 process_id: str | None = None, **limits):
        super().__init__(max_running, worker, context, **limits)
        self.work_dir = Path(work_dir)
        self.heartbeat_s = heartbeat_s
        self.queue = TrainingQueue(store, lease_s=lease_s)
        self.id = process_id or f"{socket.gethostname()[:32]}-{os.getpid()}-{secrets.token_hex(4)}"
        self._lock = threading.Lock()
        # One claim at a time in this process (slots are counted here); re-entrant: a worker that fails to start
        # frees its slot and claims the next job from inside the claim.
        self._claiming = threading.RLock()
        self._mine: dict[int, TrainingJob] = {}  # the unfinished jobs this process asked for
        self._positions: dict[int, int] = {}  # the queue position each of them was last shown
        self._runs: dict[int, _Run] = {}  # the jobs this process's workers run
        self._closed = False
        self._wake = threading.Event()
        if self.work_dir.exists():  # leftovers of a killed process: their jobs were failed by a sweep
            shutil.rmtree(self.work_dir, ignore_errors=True)
        self.queue.heartbeat(self.id, self.max_running)  # alive before the first job names this process
        self._thread = threading.Thread(target=self._loop, name="kinetix-training-queue", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ asking

    def submit(self, level_path: str | os.PathLike, out_dir: str | os.PathLike, *, steps: int,
               options: dict | None = None, on_update: Callable[[TrainingJob], None] | None = None,
               on_done: Callable[[TrainingJob], None] | None = None, client: str | None = None) -> TrainingJob:
        """Queue a run in the shared queue (TrainingPool.submit's contract); it starts at once when this process has
        a free worker and the client may start one. Raises TrainingRefused beyond a limit, counted over every
        process."""
        if steps < 1:
            raise ValueError(f"steps must be positive, got {steps}")
        if self._closed:
            raise RuntimeError("the training pool is shut down")
        level_json = Path(level_path).read_text(encoding="utf-8")
        options = dict(options or {})
        client = client or f"job:{self.id}:{secrets.token_hex(4)}"
        job_id = self.queue.submit(client=client, owner=self.id, steps=int(steps), level_json=level_json,
                                   options=options, limits=Limits(self.max_queued, self.per_client,
                                                                  self.per_client_waiting))
        job = TrainingJob(job_id, Path(level_path), Path(out_dir), int(steps), options, on_update, on_done,
                          client=client)
        with self._lock:
            self._mine[job_id] = job
        self._fill()
        self._wake.set()
        return job

    def cancel(self, job: TrainingJob) -> None:
        """Stop a run, wherever it runs: a queued one never starts; a running one's worker is terminated (at once
        here, within a loop of its process elsewhere)."""
        if job.finished:
            return
        job._cancel.set()
        state = self.queue.cancel(job.id)
        with self._lock:
            run = self._runs.get(job.id)
        if run is not None:
            run.stop.set()
        if state == "cancelled" and job.state == "queued":
            self._end(job, "cancelled")
        self._wake.set()

    def position(self, job: TrainingJob) -> int:
        """0 while running (or finished), else the job's expected place in the shared queue (1 = next)."""
        if job.state != "queued":
            return 0
        order = self.queue.order(self.per_client)
        return order.index(job.id) + 1 if job.id in order else 0

    def waits_for_own_run(self, job: TrainingJob) -> bool:
        return job.state == "queued" and self.queue.running_of(job.client) >= self.per_client

    def workers(self) -> int:
        """Runs at once over every live process."""
        return self.queue.slots()

    def jobs(self) -> list[TrainingJob]:
        """The unfinished jobs this process asked for."""
        with self._lock:
            return list(self._mine.values())

    def close(self) -> None:
        """Cancel the jobs this process asked for, give back those it ran for others, stop its workers."""
        with self._lock:
            self._closed = True
            mine = list(self._mine.values())
            runs = list(self._runs.values())
        try:
            self.queue.leave(self.id)
        except Exception:  # the database is gone: the jobs end here all the same (their rows age out)
            log.exception("could not leave the training queue")
        for job in mine:
            try:
                self.cancel(job)
            except Exception:
                log.exception("could not cancel training job %d", job.id)
                self._end(job, "cancelled")
        for run in runs:
            if run.owner != self.id:
                run.leaving.set()
            run.stop.set()
        for run in runs:
            if run.process is not None:
                run.process.join(timeout=SETTLE_S)
        deadline = time.monotonic() + SETTLE_S
        while self._runs and time.monotonic() < deadline:
            time.sleep(0.05)
        for job in mine:  # the runs this process ran ended above; those elsewhere end when their worker sees it
            try:
                self._watch_until(job, deadline)
            except Exception:
                log.exception("could not follow training job %d to its end", job.id)
                self._end(job, "cancelled")
        self._wake.set()
        self._thread.join(timeout=10)

    def _watch_until(self, job: TrainingJob, deadline: float) -> None:
        while not job.finished and time.monotonic() < deadline:
            self._watch()
            if not job.finished:
                time.sleep(WATCH_S)
        if not job.finished:  # its worker elsewhere did not answer in time: the job ends here for its tab
            self._end(job, "cancelled")

    # ------------------------------------------------------------------ the loop

    def _loop(self) -> None:
        beat = claimed = time.monotonic()
        while not self._closed:
            self._wake.wait(WATCH_S)
            self._wake.clear()
            now = time.monotonic()
            try:
                if now - beat >= self.heartbeat_s:
                    beat = now
                    self.queue.heartbeat(self.id, self.max_running)
                    self.queue.sweep()
                self._watch()
                with self._lock:
                    running = list(self._runs.values())
                if running:
                    flagged = self.queue.cancelled(self.id)
                    for run in running:
                        if run.job_id in flagged:
                            run.stop.set()
                if now - claimed >= CLAIM_EVERY_S and len(running) < self.max_running:
                    claimed = now
                    if self.queue.has_queued():  # a plain read first: the claim takes the queue's lock
                        self._fill()
            except Exception:  # a lost database connection must not end the loop: the next round tries again
                log.exception("training queue loop failed; trying again")

    def _watch(self) -> None:
        """Bring this process's own jobs up to date from their rows and tell their tabs."""
        with self._lock:
            mine = dict(self._mine)
        if not mine:
            return
        rows = self.queue.states(list(mine))
        order = None
        for job_id, job in mine.items():
            row = rows.get(job_id)
            if row is None:  # forgotten by a sweep (cannot happen to an unfinished job within the retention)
                job.error = "the training job was removed from the queue"
                self._end(job, "failed")
                continue
            changed = False
            if row.progress_n > len(job.progress):
                job.progress = self.queue.progress(job_id)
                changed = True
            if row.state == "running" and job.state == "queued":
                job.state, changed = "running", True
            if row.state == "queued":
                if order is None:
                    order = self.queue.order(self.per_client)
                position = order.index(job_id) + 1 if job_id in order else 0
                if self._positions.get(job_id) != position:
                    self._positions[job_id] = position
                    changed = job.state == "queued" or changed
                if job.state == "running":  # given back by a worker that shut down: waiting again
                    job.state, job.progress, changed = "queued", [], True
            if changed:
                job.notify()
            if row.state in ("done", "failed", "cancelled"):
                job.result = json.loads(row.result) if row.result else None
                job.error = row.error
                self._end(job, self._receive(job) if row.state == "done" else row.state)

    def _receive(self, job: TrainingJob) -> str:
        """Fetch a done job's checkpoint into its out_dir; its state ("failed" with the reason if that fails)."""
        data = self.queue.take_checkpoint(job.id)
        target = job.out_dir / "checkpoint"
        if target.is_dir():  # trained here: the worker left it in place already
            return "done"
        try:
            if data is None:
                raise CheckpointError("the finished run stored no checkpoint")
            job.out_dir.mkdir(parents=True, exist_ok=True)
            unpack_checkpoint(data, target)
            return "done"
        except (CheckpointError, OSError) as error:
            job.error = f"the trained agent could not be fetched: {error}"
            return "failed"

    def _end(self, job: TrainingJob, state: str) -> None:
        """A job this process asked for ended: its final state, then on_done once (TrainingPool's contract)."""
        with self._lock:
            if self._mine.pop(job.id, None) is None:
                return  # ended already (a cancel and the loop both saw it)
            self._positions.pop(job.id, None)
        job.state = state
        if state == "cancelled":
            shutil.rmtree(job.out_dir, ignore_errors=True)  # a cancelled run keeps nothing
        job.settle()

    # ------------------------------------------------------------------ working

    def _fill(self) -> None:
        """Claim and start jobs while this process has a free worker."""
        with self._claiming:
            while True:
                with self._lock:
                    if self._closed or len(self._runs) >= self.max_running:
                        return
                row = self.queue.claim(self.id, per_client=self.per_client)
                if row is None:
                    return
                self._start(row)

    def _start(self, row) -> None:
        run = _Run(int(row.id), row.owner, self.work_dir / f"job-{row.id}-{secrets.token_hex(3)}")
        with self._lock:
            self._runs[run.job_id] = run
            mirror = self._mine.get(run.job_id)
            closing = self._closed
        if closing:  # claimed while close() began: back to the queue (a job of this process's is cancelled there)
            self._finished(run, "requeue")
            return
        if mirror is not None:  # this process asked for it: the tab sees it start at once
            mirror.state = "running"
            run.work_dir = mirror.out_dir  # train straight into the asker's run folder (no copy of the result)
        messages = self._mp.Queue()
        try:
            run.work_dir.mkdir(parents=True, exist_ok=True)
            level_path = run.work_dir / "level.json"
            if mirror is None or not level_path.is_file():
                level_path.write_text(row.level_json, encoding="utf-8")
            process = self._mp.Process(target=self.worker, name=f"kinetix-train-{run.job_id}", daemon=True,
                                       args=(str(level_path), str(run.work_dir), int(row.steps), messages,
                                             json.loads(row.options)))
            process.start()
            run.process = process  # only once started: close() joins it
        except Exception as error:
            log.exception("could not start a training worker")
            self._finished(run, "failed", error=f"could not start the worker: {error}")
            return
        if mirror is not None:
            mirror.process = run.process
            mirror.notify()
        threading.Thread(target=self._supervise, args=(run, messages), name=f"kinetix-train-{run.job_id}",
                         daemon=True).start()

    def _supervise(self, run: _Run, messages) -> None:
        """TrainingPool._supervise for a queued row: progress to the row, the result and checkpoint at the end."""
        process, progress, result, error = run.process, [], None, None
        reported, unreported = 0.0, False
        while True:
            try:
                kind, body = messages.get(timeout=POLL_S)
            except queue_module.Empty:
                if run.stop.is_set() or not process.is_alive():
                    break
                if unreported and time.monotonic() - reported >= REPORT_EVERY_S:  # the rest of a throttled batch
                    reported, unreported = time.monotonic(), False
                    if self._report(run, progress):
                        run.stop.set()
                continue
            except (EOFError, OSError):
                break
            if kind == "progress":
                progress.append(body)
                unreported = True
                if messages.empty() and time.monotonic() - reported >= REPORT_EVERY_S:
                    reported, unreported = time.monotonic(), False
                    if self._report(run, progress):
                        run.stop.set()
                        break
            elif kind == "done":
                result = body
                break
            elif kind == "error":
                error = body
                break
        end_worker(process, terminate=run.stop.is_set())
        if progress:
            self._report(run, progress)
        if run.leaving.is_set():
            self._finished(run, "requeue")
        elif run.stop.is_set():
            self._finished(run, "cancelled")
        elif result is not None:
            try:
                checkpoint = pack_checkpoint(run.work_dir / "checkpoint")
            except (CheckpointError, OSError) as problem:
                self._finished(run, "failed", error=f"the run wrote no checkpoint: {problem}")
            else:
                self._finished(run, "done", result=result, checkpoint=checkpoint)
        else:
            self._finished(run, "failed", error=error or f"the training worker exited with code {process.exitcode}")

    def _report(self, run: _Run, progress: list[dict]) -> bool:
        try:
            return self.queue.report(run.job_id, self.id, progress)
        except Exception:
            log.exception("could not store training progress")
            return False

    def _finished(self, run: _Run, state: str, **values) -> None:
        """Store a run's end (or give it back), free its worker slot and take the next job."""
        try:
            if state == "requeue" and not self.queue.requeue(run.job_id, self.id):
                state = "cancelled"  # it was cancelled meanwhile: it ends instead of waiting again
            if state != "requeue" and not self.queue.finish(run.job_id, self.id, state, **values):
                log.warning("training job %d was ended elsewhere meanwhile (lease expired?)", run.job_id)
        except Exception:
            log.exception("could not store the end of training job %d", run.job_id)
        with self._lock:
            self._runs.pop(run.job_id, None)
            mine = run.job_id in self._mine
        if not mine:
            shutil.rmtree(run.work_dir, ignore_errors=True)  # the result travels in the row
        self._wake.set()
        if not self._closed:
            self._fill()

