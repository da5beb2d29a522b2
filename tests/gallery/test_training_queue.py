"""The browser's training queue in the gallery database (server.agents.queue, server.agents.shared_pool), on SQLite
and PostgreSQL: two Store objects on one database stand for two server processes (a third, real process is
killed with SIGKILL). Jobs are claimed once; the per-person limits and the queue cap count across processes; a job
asked for on A and trained on B reports its progress to A, its checkpoint reaches A, and A cancels it; a dead
worker's job fails with a clear message; a clean shutdown gives the jobs it ran back to the queue. The training is
the cheap fake worker of tests/server (a spawned process, no JAX)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from server.agents.queue import DEAD_OWNER, Limits, TrainingQueue
from server.agents.shared_pool import SharedTrainingPool
from server.agents.training import TrainingRefused
from tests.server.conftest import wait_until
from tests.server.fake_training import fake_train_worker

ROOT = Path(__file__).resolve().parents[2]
ROOMY = Limits(max_queued=100, per_client=1, per_client_waiting=100)


@pytest.fixture
def pools(two, tmp_path):
    """A factory of SharedTrainingPools with the fake worker (closed after the test), fast heartbeats."""
    made = []

    def make(store, name, max_running=1, **kwargs):
        pool = SharedTrainingPool(store, max_running, worker=fake_train_worker, work_dir=tmp_path / name / ".work",
                                  heartbeat_s=0.2, process_id=name, **kwargs)
        made.append(pool)
        return pool

    yield make
    for pool in made:
        pool.close()


def _submit(pool, tmp_path, name, client=None, **options):
    level = tmp_path / "level.json"
    level.write_text('{"name": "a level"}')
    updates = []
    job = pool.submit(level, tmp_path / "runs" / name, steps=4000, client=client,
                      options={"release": str(tmp_path / f"release-{name}"), **options},
                      on_update=lambda job: updates.append((job.state, len(job.progress))))
    return job, updates


def test_two_processes_never_claim_the_same_job(two):
    queues = [TrainingQueue(store) for store in two]
    for queue, name in zip(queues, "ab", strict=True):
        queue.heartbeat(name, slots=100)
    submitted = {queues[i % 2].submit(client=f"client-{i}", owner="ab"[i % 2], steps=100, level_json="{}",
                                      options={}, limits=ROOMY) for i in range(24)}
    claimed: dict[str, list[int]] = {}
    start = threading.Barrier(4)

    def claim_all(queue, worker):
        start.wait(timeout=60)  # all at once
        while (row := queue.claim(worker, per_client=1)) is not None:
            claimed.setdefault(worker, []).append(int(row.id))
            time.sleep(0.005)  # a worker starting its run: the others claim meanwhile

    threads = [threading.Thread(target=claim_all, args=(queues[i % 2], f"worker-{i}")) for i in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    ids = [job_id for jobs in claimed.values() for job_id in jobs]
    assert sorted(ids) == sorted(submitted), "every job claimed exactly once"
    assert len(claimed) >= 2, "both processes claimed some"


def test_the_per_person_limit_holds_when_two_processes_claim_at_once(two):
    """alice's two queued jobs, four claimers on two processes: only one of hers runs (per_client 1)."""
    queues = [TrainingQueue(store) for store in two]
    for queue, name in zip(queues, "ab", strict=True):
        queue.heartbeat(name, slots=100)
    for owner in "ab":
        queues[0].submit(client="alice", owner=owner, steps=100, level_json="{}", options={}, limits=ROOMY)
    rows = []
    threads = [threading.Thread(target=lambda q=queues[i % 2], i=i: rows.append(q.claim(f"w{i}", per_client=1)))
               for i in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    assert len([row for row in rows if row is not None]) == 1


def test_limits_count_across_processes(two, pools, tmp_path):
    a = pools(two[0], "a", max_queued=2)
    b = pools(two[1], "b", max_queued=2)
    a1, _ = _submit(a, tmp_path, "a1", client="alice")
    assert a1.state == "running", "A's free worker takes its own job at once"
    a2, _ = _submit(b, tmp_path, "a2", client="alice")
    assert a2.state == "queued" and b.waits_for_own_run(a2), "alice runs one already (on A), though B is free"
    with pytest.raises(TrainingRefused, match="already have 2 training runs going or waiting"):
        _submit(a, tmp_path, "a3", client="alice")
    b1, _ = _submit(b, tmp_path, "b1", client="bob")
    assert b1.state == "running", "another person takes B's free worker"
    c1, _ = _submit(a, tmp_path, "c1", client="carol")
    assert c1.state == "queued" and not a.waits_for_own_run(c1)
    with pytest.raises(TrainingRefused, match=r"the training queue is full \(2 runs waiting for 2 workers\)"):
        _submit(b, tmp_path, "d1", client="dave")
    assert a.workers() == b.workers() == 2
    assert [a.position(c1), b.position(a2)] == [1, 2], "carol (never served) goes before alice's second run"
    a.cancel(a1)  # A's worker frees: carol's run (asked on A) starts there, alice's waits on
    wait_until(lambda: c1.state == "running")
    assert a1.settled.wait(30) and a1.state == "cancelled" and not a1.process.is_alive()
    assert a2.state == "queued" and b.position(a2) == 1


def test_a_job_asked_on_a_runs_on_b_reports_to_a_and_is_cancelled_from_a(two, pools, tmp_path):
    a = pools(two[0], "a", max_running=0)  # A trains nothing: B's worker must take A's jobs
    b = pools(two[1], "b")
    job, updates = _submit(a, tmp_path, "cancelled")
    wait_until(lambda: len(job.progress) == 3, 60)  # B runs it; its progress reaches A's job
    assert job.state == "running" and job.process is None, "the worker is not A's"
    assert list((tmp_path / "b" / ".work").glob("job-*/started")), "the run started in B's work folder"
    assert ("running", 3) in updates and 0.7 < job.fraction < 0.8
    a.cancel(job)
    assert job.settled.wait(30) and job.state == "cancelled"
    wait_until(lambda: not list((tmp_path / "b" / ".work").glob("job-*")), 30)  # B terminated it and kept nothing
    assert not (tmp_path / "runs" / "cancelled").exists()

    (tmp_path / "release-done").touch()
    done, _ = _submit(a, tmp_path, "done")
    assert done.settled.wait(60) and done.state == "done", done.error
    assert done.result["solve_rate"] == 0.75 and len(done.progress) == 3
    assert (tmp_path / "runs" / "done" / "checkpoint" / "config.json").read_text() == '{"fake": true}', \
        "the checkpoint trained on B is in A's run folder"
    wait_until(lambda: not list((tmp_path / "b" / ".work").glob("job-*")), 30)
    assert a.jobs() == [] and b.jobs() == []


def test_a_clean_shutdown_gives_the_jobs_it_ran_for_others_back_to_the_queue(two, pools, tmp_path):
    a = pools(two[0], "a", max_running=0)
    b = pools(two[1], "b")
    job, _ = _submit(a, tmp_path, "given-back")
    wait_until(lambda: len(job.progress) == 3, 60)
    b.close()
    wait_until(lambda: job.state == "queued" and job.progress == [], 30)  # waiting again, from the start
    (tmp_path / "release-given-back").touch()
    c = pools(two[1], "c")  # another process takes it up
    assert job.settled.wait(60) and job.state == "done"
    assert c.jobs() == []


def test_a_dead_owners_jobs_are_cancelled_and_a_dead_workers_job_fails(two):
    alive = TrainingQueue(two[0], lease_s=1.0)
    alive.heartbeat("alive", slots=1)
    alive.heartbeat("gone", slots=1)
    orphan = alive.submit(client="x", owner="gone", steps=10, level_json="{}", options={}, limits=ROOMY)
    running = alive.submit(client="y", owner="alive", steps=10, level_json="{}", options={}, limits=ROOMY)
    claimed = {alive.claim("gone", per_client=1).id, alive.claim("gone", per_client=1).id}
    assert claimed == {orphan, running}
    time.sleep(1.2)
    alive.heartbeat("alive", slots=1)
    assert alive.sweep()["failed"] == 2
    states = alive.states([orphan, running])
    assert states[running].state == "failed" and "stopped (no sign of life for 1 s)" in states[running].error
    queued = alive.submit(client="z", owner="gone", steps=10, level_json="{}", options={}, limits=ROOMY)
    assert alive.sweep()["orphaned"] == 1
    assert alive.states([queued])[queued].state == "cancelled" and alive.states([queued])[queued].error == DEAD_OWNER


WORKER_PROCESS = """
import sys, time
from server.agents.shared_pool import SharedTrainingPool
from server.gallery.store import Store
from tests.server.fake_training import fake_train_worker
pool = SharedTrainingPool(Store(sys.argv[1], seed_dir=None), 1, worker=fake_train_worker, work_dir=sys.argv[2],
                          heartbeat_s=0.2, process_id="doomed")
print("ready", flush=True)
time.sleep(600)
"""


def test_a_job_whose_worker_process_is_killed_fails_with_a_clear_message(db_url, two, pools, tmp_path):
    a = pools(two[0], "a", max_running=0, lease_s=3.0)
    doomed = subprocess.Popen([sys.executable, "-c", WORKER_PROCESS, db_url, str(tmp_path / "doomed")],
                              cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.PIPE,
                              text=True, start_new_session=True)
    try:
        assert doomed.stdout.readline().strip() == "ready"
        job, _ = _submit(a, tmp_path, "orphaned")
        wait_until(lambda: len(job.progress) == 3, 60)  # the other process runs it
        os.killpg(doomed.pid, signal.SIGKILL)  # the process and its worker, as a crashed host
        doomed.wait(timeout=30)
        assert job.settled.wait(30), "the lease ran out and A's sweep ended the job"
        assert job.state == "failed"
        assert "server process running this training stopped" in job.error and "Train on this level" in job.error
    finally:
        if doomed.poll() is None:
            os.killpg(doomed.pid, signal.SIGKILL)
            doomed.wait(timeout=30)
