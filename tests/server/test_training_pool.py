"""server.agents.training.TrainingPool with a cheap fake worker (spawned processes, no JAX): the cap queues runs, queue
positions move up, cancel stops queued and running runs, a dying worker is reported, progress reaches the caller;
per-client limits, the global queue cap and the round-robin order across clients (issue 26)."""

from __future__ import annotations

import threading
import time

import pytest
from fake_training import fake_train_worker

from server.agents.training import TrainingPool, TrainingRefused


def _wait(predicate, timeout=60.0):
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError("condition not reached")
        time.sleep(0.02)


@pytest.fixture
def pool():
    pool = TrainingPool(max_running=1, worker=fake_train_worker)
    yield pool
    pool.close()


def _submit(pool, tmp_path, name, client=None, **options):
    done = threading.Event()
    updates = []
    job = pool.submit(tmp_path / "level.json", tmp_path / name, steps=4000, client=client,
                      options={"release": str(tmp_path / f"release-{name}"), **options},
                      on_update=lambda job: updates.append((job.state, len(job.progress))),
                      on_done=lambda job: done.set())
    return job, done, updates


def test_the_cap_queues_a_second_run_until_the_first_finishes(pool, tmp_path):
    first, first_done, first_updates = _submit(pool, tmp_path, "a")
    second, second_done, second_updates = _submit(pool, tmp_path, "b")
    third, _, third_updates = _submit(pool, tmp_path, "c")
    assert first.state == "running" and pool.position(first) == 0
    assert second.state == "queued" and pool.position(second) == 1 and pool.position(third) == 2
    _wait(lambda: len(first.progress) == 3)
    assert 0.7 < first.fraction < 0.8  # 3000 of 4000 steps
    assert not (tmp_path / "b" / "started").exists(), "a queued run must not start beyond the cap"
    _wait(lambda: any(n == 3 for _, n in first_updates))  # progress reached the caller
    (tmp_path / "release-a").touch()
    assert first_done.wait(60)
    assert first.state == "done" and first.result["solve_rate"] == 0.75 and first.fraction == 1.0
    assert (tmp_path / "a" / "checkpoint" / "config.json").is_file()
    _wait(lambda: second.state == "running")
    assert pool.position(third) == 1, "the queue moved up"
    _wait(lambda: ("queued", 0) in third_updates)  # a queued run is told when its position changes
    _wait(lambda: (tmp_path / "b" / "started").exists())
    pool.cancel(third)
    assert third.state == "cancelled" and third.process is None, "a cancelled queued run never starts"
    (tmp_path / "release-b").touch()
    assert second_done.wait(60) and second.state == "done"
    assert second_updates[0] == ("running", 0)


def test_cancel_terminates_a_running_worker_and_keeps_nothing(pool, tmp_path):
    job, done, _ = _submit(pool, tmp_path, "a")
    _wait(lambda: len(job.progress) == 3)
    pool.cancel(job)
    assert done.wait(30)
    assert job.state == "cancelled" and not job.process.is_alive()
    assert not (tmp_path / "a").exists()
    follower, follower_done, _ = _submit(pool, tmp_path, "b")  # the slot is free again
    assert follower.state == "running"
    pool.cancel(follower)
    assert follower_done.wait(30)


def test_a_worker_that_dies_is_reported_as_failed(pool, tmp_path):
    job, done, _ = _submit(pool, tmp_path, "a", fail=True)
    (tmp_path / "release-a").touch()
    assert done.wait(60)
    assert job.state == "failed" and "exited with code 3" in job.error


def test_the_queue_takes_turns_between_clients_not_first_come_first_served(tmp_path):
    pool = TrainingPool(max_running=1, worker=fake_train_worker, per_client=1, per_client_waiting=3)
    try:
        a1, a1_done, _ = _submit(pool, tmp_path, "a1", client="alice")
        a2, a2_done, _ = _submit(pool, tmp_path, "a2", client="alice")
        a3, a3_done, _ = _submit(pool, tmp_path, "a3", client="alice")
        b1, b1_done, _ = _submit(pool, tmp_path, "b1", client="bob")
        c1, c1_done, _ = _submit(pool, tmp_path, "c1", client="carol")
        b2, b2_done, _ = _submit(pool, tmp_path, "b2", client="bob")
        assert a1.state == "running"
        # alice was served last: bob and carol go first, then one run of each client in turn (FIFO would be
        # a2, a3, b1, c1, b2).
        expected = [b1, c1, a2, b2, a3]
        assert [pool.position(job) for job in expected] == [1, 2, 3, 4, 5]
        started = [a1]
        for job, done in ((a1, a1_done), (b1, b1_done), (c1, c1_done), (a2, a2_done), (b2, b2_done)):
            pool.cancel(job)  # frees the worker: the next run in turn starts
            assert done.wait(30)
            _wait(lambda: any(other.state == "running" for other in expected if other not in started))
            started += [other for other in expected if other.state == "running" and other not in started]
        assert started == [a1, *expected]
        pool.cancel(a3)
        assert a3_done.wait(30)
    finally:
        pool.close()


def test_per_client_limits_and_the_queue_cap_refuse_with_a_clear_message(tmp_path):
    pool = TrainingPool(max_running=2, worker=fake_train_worker, max_queued=2, per_client=1, per_client_waiting=1)
    try:
        a1, _, _ = _submit(pool, tmp_path, "a1", client="alice")
        a2, _, _ = _submit(pool, tmp_path, "a2", client="alice")
        assert a1.state == "running"
        assert a2.state == "queued" and pool.waits_for_own_run(a2), "one running run per client, a worker is free"
        with pytest.raises(TrainingRefused, match="already have 2 training runs going or waiting"):
            _submit(pool, tmp_path, "a3", client="alice")
        assert not (tmp_path / "a3").exists()
        b1, _, _ = _submit(pool, tmp_path, "b1", client="bob")
        assert b1.state == "running", "another client takes the free worker"
        c1, _, _ = _submit(pool, tmp_path, "c1", client="carol")
        assert c1.state == "queued" and not pool.waits_for_own_run(c1)
        with pytest.raises(TrainingRefused, match=r"the training queue is full \(2 runs waiting"):
            _submit(pool, tmp_path, "d1", client="dave")
        assert len(pool.jobs()) == 4
        pool.cancel(a1)  # alice's worker frees: carol (never served) goes before alice's second run
        _wait(lambda: c1.state == "running")
        assert a2.state == "queued" and pool.position(a2) == 1
    finally:
        pool.close()
    assert all(not job.process.is_alive() for job in (a1, b1, c1))


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="at least one"):
        TrainingPool(max_running=0)
    with pytest.raises(ValueError, match="per client"):
        TrainingPool(per_client=0)
    with pytest.raises(ValueError, match="cannot be negative"):
        TrainingPool(max_queued=-1)
    pool = TrainingPool(max_running=1, worker=fake_train_worker)
    with pytest.raises(ValueError, match="steps must be positive"):
        pool.submit("level.json", "out", steps=0)
    pool.close()
    with pytest.raises(RuntimeError, match="shut down"):
        pool.submit("level.json", "out", steps=10)


def test_the_real_worker_reports_a_bad_level_as_a_clear_failure(tmp_path):
    from server.agents.training import train_worker

    bad = tmp_path / "level.json"
    bad.write_text("{not json")
    pool = TrainingPool(max_running=1, worker=train_worker)
    done = threading.Event()
    try:
        job = pool.submit(bad, tmp_path / "run", steps=1024, on_done=lambda job: done.set())
        assert done.wait(180)
        assert job.state == "failed"
        assert "LevelError" in job.error and "level.json" in job.error, job.error
    finally:
        pool.close()
