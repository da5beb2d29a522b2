"""The browser's training queue as rows of the gallery database (table `training_jobs`, gallery migration 6), so
that several `kinetix serve` processes on one PostgreSQL database share one queue (docs/deploy.md): any process's
worker takes the next job, and the per-person limits and the queue cap count across all of them.

    queue = TrainingQueue(store)
    job_id = queue.submit(client="author:ab12", owner=me, steps=4000, level_json=doc, options={}, limits=rules)
    row = queue.claim(me, per_client=1)     # the next job in turn, now "running" on `me`; None when nothing may start
    queue.report(job_id, me, progress)      # True when the job was cancelled meanwhile
    queue.finish(job_id, me, "done", result=summary, checkpoint=pack_checkpoint(...))
    queue.cancel(job_id)                    # a queued job ends now; a running one is flagged for its worker

A row holds what a job is (level document, settings, who asked: `client` for the limits and `owner`, the process
whose tab asked and shows it), its state (queued, running, done, failed, cancelled), its progress (the worker's
progress dicts as JSON, `progress_n` of them), its result (summary, error, and the trained checkpoint as a blob,
server.gallery.checkpoints) and who runs it (`worker`, `heartbeat`).

Atomic claims: every write that decides who runs what (submit, claim) runs under one lock, PostgreSQL's
transaction-level advisory lock QUEUE_LOCK (SQLite's BEGIN IMMEDIATE locks the whole database already), and the
claim itself is a conditional UPDATE (`... WHERE id = :id AND state = 'queued'`), so a job is claimed once. Row locks
alone (SELECT ... FOR UPDATE SKIP LOCKED) would let two processes claim two different jobs of one person at the
same moment, each seeing that person run nothing: the per-person limit spans rows, so the decision takes one lock.
It is taken once per submit and per claim, a few times a minute at most.

Liveness: every process upserts its row in `training_workers` (its slots and a heartbeat) and refreshes the
heartbeat of the jobs it runs every HEARTBEAT_S. `sweep` (run by every process) then:
- fails a running job whose heartbeat is older than the lease, with a message saying so. Not re-queued: the run
  cannot resume (its training state was in the dead process's data folder), a job that crashed its process would
  crash the next one too, and the person who asked sees why and can press Train again;
- cancels the jobs of an owner process that stopped (their tab went with it; nobody would see the result);
- deletes finished rows after RETENTION_S (kept that long for the round-robin's memory of who was served).
"""

from __future__ import annotations

import dataclasses
import json
import logging

from sqlalchemy import Connection, case, delete, func, select, text, update

from server.agents.training import check_limits, projected_order
from server.gallery.schema import now_ms, training_jobs_t, training_workers_t

log = logging.getLogger(__name__)

HEARTBEAT_S = 5.0  # how often a process says it is alive, for itself and the jobs it runs
LEASE_S = 60.0  # a process or running job silent this long is dead (a loaded 2-core host stalls seconds, not a minute)
RETENTION_S = 3600.0  # finished jobs are kept this long (the round-robin remembers who was served an hour)
QUEUE_LOCK = 0x6B74726E  # PostgreSQL advisory lock key of the queue's decisions (any constant, not the migrations')
FINISHED = ("done", "failed", "cancelled")
MAX_CLIENT = 80  # the column's width
DEAD_WORKER = ("the server process running this training stopped (no sign of life for {lease:.0f} s); nothing of "
               "the run was kept: press Train on this level to start it again")
DEAD_OWNER = "the server process of the tab that asked for this training stopped"


@dataclasses.dataclass(frozen=True)
class Limits:
    """The queue's limits, as TrainingPool has them (server.agents.training.check_limits)."""

    max_queued: int
    per_client: int
    per_client_waiting: int


class TrainingQueue:
    """Training jobs in the gallery database. Thread-safe (each call is one transaction); one per process."""

    def __init__(self, store, *, lease_s: float = LEASE_S, retention_s: float = RETENTION_S):
        self.store = store
        self.lease_ms = int(lease_s * 1000)
        self.retention_ms = int(retention_s * 1000)

    def _locked(self, conn: Connection) -> None:
        if self.store.dialect == "postgresql":
            conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": QUEUE_LOCK})

    # ------------------------------------------------------------ asking

    def submit(self, *, client: str, owner: str, steps: int, level_json: str, options: dict, limits: Limits) -> int:
        """Queue a job unless a limit refuses it (TrainingRefused, nothing written); returns its id."""
        client = client[:MAX_CLIENT]
        options_json = json.dumps(options, allow_nan=False)
        with self.store._write() as conn:
            self._locked(conn)
            counts = self._counts(conn, client)
            check_limits(counts["mine_running"], counts["mine_queued"], counts["running"], counts["queued"],
                         workers=self._slots(conn), per_client=limits.per_client,
                         per_client_waiting=limits.per_client_waiting, max_queued=limits.max_queued)
            stamp = now_ms()
            return int(conn.execute(training_jobs_t.insert().values(
                client=client, owner=owner, worker=None, state="queued", steps=int(steps), level_json=level_json,
                options=options_json, progress="[]", progress_n=0, cancel=False, created=stamp)
                .returning(training_jobs_t.c.id)).scalar_one())

    def _counts(self, conn: Connection, client: str) -> dict[str, int]:
        c = training_jobs_t.c
        rows = conn.execute(select(c.state, func.count(), func.sum(case((c.client == client, 1), else_=0)))
                            .where(c.state.in_(("queued", "running"))).group_by(c.state)).all()
        counts = {"queued": 0, "running": 0, "mine_queued": 0, "mine_running": 0}
        for state, n, mine in rows:
            counts[state], counts[f"mine_{state}"] = int(n), int(mine or 0)
        return counts

    def _slots(self, conn: Connection) -> int:
        """Runs at once over every live process (the sum of their worker slots)."""
        alive = now_ms() - self.lease_ms
        return int(conn.execute(select(func.coalesce(func.sum(training_workers_t.c.slots), 0))
                                .where(training_workers_t.c.heartbeat >= alive)).scalar_one())

    def slots(self) -> int:
        with self.store._read() as conn:
            return self._slots(conn)

    def cancel(self, job_id: int) -> str | None:
        """Cancel a job: a queued one is cancelled now, a running one is flagged for its worker (which stops it and
        marks it cancelled). Returns the job's state after the call (None: no such job)."""
        with self.store._write() as conn:
            stamp = now_ms()
            if conn.execute(update(training_jobs_t).where(training_jobs_t.c.id == job_id,
                                                          training_jobs_t.c.state == "queued")
                            .values(state="cancelled", cancel=True, finished=stamp)).rowcount:
                return "cancelled"
            conn.execute(update(training_jobs_t).where(training_jobs_t.c.id == job_id,
                                                       training_jobs_t.c.state == "running").values(cancel=True))
            return conn.execute(select(training_jobs_t.c.state).where(training_jobs_t.c.id == job_id)).scalar()

    # ------------------------------------------------------------ watching (the asking process)

    def states(self, job_ids: list[int]) -> dict[int, object]:
        """id -> row (state, progress_n, result, error, worker) of the given jobs, without progress or checkpoint."""
        if not job_ids:
            return {}
        c = training_jobs_t.c
        with self.store._read() as conn:
            rows = conn.execute(select(c.id, c.state, c.progress_n, c.result, c.error, c.worker)
                                .where(c.id.in_(job_ids))).all()
        return {int(row.id): row for row in rows}

    def progress(self, job_id: int) -> list[dict]:
        with self.store._read() as conn:
            value = conn.execute(select(training_jobs_t.c.progress).where(training_jobs_t.c.id == job_id)).scalar()
        return json.loads(value) if value else []

    def take_checkpoint(self, job_id: int) -> bytes | None:
        """The trained checkpoint of a finished job, removed from the row (the asking process keeps it now)."""
        with self.store._write() as conn:
            data = conn.execute(select(training_jobs_t.c.checkpoint).where(training_jobs_t.c.id == job_id)).scalar()
            conn.execute(update(training_jobs_t).where(training_jobs_t.c.id == job_id).values(checkpoint=None))
        return None if data is None else bytes(data)

    def order(self, per_client: int) -> list[int]:
        """The queued jobs' ids in the order they would start (round-robin across clients, as TrainingPool)."""
        with self.store._read() as conn:
            queued, served, _ = self._queue_state(conn)
        return [row.id for row in projected_order(queued, served, per_client)]

    def running_of(self, client: str) -> int:
        with self.store._read() as conn:
            return int(conn.execute(select(func.count()).where(training_jobs_t.c.client == client[:MAX_CLIENT],
                                                               training_jobs_t.c.state == "running")).scalar_one())

    def _queue_state(self, conn: Connection) -> tuple[list, dict[str, int], list]:
        """(queued rows, client -> its last start, running rows); rows have .id and .client."""
        c = training_jobs_t.c
        active = conn.execute(select(c.id, c.client, c.state).where(c.state.in_(("queued", "running")))
                              .order_by(c.id)).all()
        queued = [row for row in active if row.state == "queued"]
        clients = {row.client for row in queued}
        served = {}
        if clients:
            served = {client: int(last) for client, last in conn.execute(
                select(c.client, func.max(c.started)).where(c.client.in_(clients), c.started.is_not(None))
                .group_by(c.client))}
        return queued, served, [row for row in active if row.state == "running"]

    # ------------------------------------------------------------ working (any process)

    def has_queued(self) -> bool:
        with self.store._read() as conn:
            return conn.execute(select(training_jobs_t.c.id).where(training_jobs_t.c.state == "queued")
                                .limit(1)).first() is not None

    def claim(self, worker: str, *, per_client: int):
        """Take the next job in turn for `worker` (state running, its heartbeat now) and return its row (id,
        client, owner, steps, level_json, options); None when no queued job may start (none, or every waiting
        client already runs `per_client`)."""
        from server.agents.training import pick_next

        c = training_jobs_t.c
        with self.store._write() as conn:
            self._locked(conn)
            queued, served, running = self._queue_state(conn)
            chosen = pick_next(queued, served, per_client, running)
            if chosen is None:
                return None
            stamp = max(now_ms(), max(served.values(), default=0) + 1)  # starts strictly ordered for the turns
            if not conn.execute(update(training_jobs_t).where(c.id == chosen.id, c.state == "queued")
                                .values(state="running", worker=worker, started=stamp, heartbeat=stamp)).rowcount:
                return None  # cannot happen under the lock; the condition keeps it true without one
            return conn.execute(select(c.id, c.client, c.owner, c.steps, c.level_json, c.options)
                                .where(c.id == chosen.id)).one()

    def report(self, job_id: int, worker: str, progress: list[dict]) -> bool:
        """Store a running job's progress so far; True if it should stop (cancelled, or no longer this worker's)."""
        c = training_jobs_t.c
        with self.store._write() as conn:
            done = conn.execute(update(training_jobs_t).where(c.id == job_id, c.worker == worker,
                                                              c.state == "running")
                                .values(progress=json.dumps(progress), progress_n=len(progress),
                                        heartbeat=now_ms())).rowcount
            if not done:
                return True
            return bool(conn.execute(select(c.cancel).where(c.id == job_id)).scalar())

    def finish(self, job_id: int, worker: str, state: str, *, result: dict | None = None, error: str | None = None,
               checkpoint: bytes | None = None) -> bool:
        """End a job this worker runs; False when it is not this worker's running job any more (a sweep failed it)."""
        if state not in FINISHED:
            raise ValueError(f"a job ends done, failed or cancelled, not {state!r}")
        c = training_jobs_t.c
        with self.store._write() as conn:
            return bool(conn.execute(update(training_jobs_t).where(c.id == job_id, c.worker == worker,
                                                                   c.state == "running")
                                     .values(state=state, result=None if result is None else json.dumps(result),
                                             error=error, checkpoint=checkpoint, finished=now_ms())).rowcount)

    def requeue(self, job_id: int, worker: str) -> bool:
        """Give a running job back to the queue (its worker's process is shutting down cleanly): it starts afresh."""
        c = training_jobs_t.c
        with self.store._write() as conn:
            return bool(conn.execute(update(training_jobs_t).where(c.id == job_id, c.worker == worker,
                                                                   c.state == "running", c.cancel.is_(False))
                                     .values(state="queued", worker=None, started=None, heartbeat=None,
                                             progress="[]", progress_n=0)).rowcount)

    def cancelled(self, worker: str) -> set[int]:
        """The running jobs of `worker` flagged for cancelling."""
        c = training_jobs_t.c
        with self.store._read() as conn:
            return {int(r[0]) for r in conn.execute(select(c.id).where(c.worker == worker, c.state == "running",
                                                                       c.cancel.is_(True)))}

    # ------------------------------------------------------------ liveness

    def heartbeat(self, process: str, slots: int) -> None:
        """This process is alive with `slots` workers, and so are the jobs it runs."""
        stamp = now_ms()
        with self.store._write() as conn:
            conn.execute(text("INSERT INTO training_workers (id, slots, heartbeat) VALUES (:i, :s, :h) "
                              "ON CONFLICT (id) DO UPDATE SET slots = excluded.slots, heartbeat = excluded.heartbeat"),
                         {"i": process, "s": int(slots), "h": stamp})
            conn.execute(update(training_jobs_t).where(training_jobs_t.c.worker == process,
                                                       training_jobs_t.c.state == "running").values(heartbeat=stamp))

    def leave(self, process: str) -> None:
        """A process shutting down: it takes no more jobs (its slots stop counting)."""
        with self.store._write() as conn:
            conn.execute(delete(training_workers_t).where(training_workers_t.c.id == process))

    def sweep(self) -> dict[str, int]:
        """Fail the running jobs of dead workers, cancel the jobs of dead owners, forget old finished jobs and dead
        processes. Returns how many of each (for the log and tests)."""
        c = training_jobs_t.c
        stamp = now_ms()
        dead_before = stamp - self.lease_ms
        alive = select(training_workers_t.c.id).where(training_workers_t.c.heartbeat >= dead_before)
        with self.store._write() as conn:
            failed = conn.execute(update(training_jobs_t).where(c.state == "running", c.heartbeat < dead_before)
                                  .values(state="failed", error=DEAD_WORKER.format(lease=self.lease_ms / 1000),
                                          finished=stamp)).rowcount
            orphaned = conn.execute(update(training_jobs_t).where(c.state == "queued", c.owner.not_in(alive))
                                    .values(state="cancelled", cancel=True, error=DEAD_OWNER, finished=stamp)).rowcount
            orphaned += conn.execute(update(training_jobs_t).where(c.state == "running", c.cancel.is_(False),
                                                                   c.owner.not_in(alive))
                                     .values(cancel=True, error=DEAD_OWNER)).rowcount
            forgotten = conn.execute(delete(training_jobs_t).where(c.state.in_(FINISHED),
                                                                   c.finished < stamp - self.retention_ms)).rowcount
            conn.execute(delete(training_workers_t).where(training_workers_t.c.heartbeat < stamp - self.retention_ms))
        if failed or orphaned:
            log.warning("training queue: %d run(s) of stopped processes failed, %d of stopped tabs' processes "
                        "cancelled", failed, orphaned)
        return {"failed": failed, "orphaned": orphaned, "forgotten": forgotten}
