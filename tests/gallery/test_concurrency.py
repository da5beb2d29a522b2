"""16 threads saving, voting and recording plays at once for 10 s lose nothing (SQLite and PostgreSQL);
a writer process killed with SIGKILL leaves a consistent database."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

from server.gallery.checks import SavedLevel, prepare_level
from server.gallery.store import Store
from tests.gallery.conftest import level_doc

THREADS = 16
WORKLOAD_SECONDS = 10.0  # how long the threads keep writing; nothing is timed


def test_sixteen_threads_lose_nothing(store: Store, db_url: str):
    # Half the threads use a second Store (its own engine and pool), as a second server process would.
    stores = [store, Store(db_url, seed_dir=None)]
    prepared = prepare_level(level_doc())  # one render; the threads exercise the database, not the renderer
    seed_ids = [store.create_level(f"seed {i}", {}, prepared=prepared)[0] for i in range(4)]
    created: list[str] = []
    plays: Counter = Counter()
    votes: dict[tuple[str, str], int] = {}
    errors: list[BaseException] = []
    lock = threading.Lock()
    stop = time.monotonic() + WORKLOAD_SECONDS

    def worker(n: int) -> None:
        rng = random.Random(n)
        db = stores[n % 2]
        token = None
        try:
            while time.monotonic() < stop:
                action = rng.random()
                with lock:
                    targets = seed_ids + created
                target = rng.choice(targets)
                if action < 0.2:
                    level_id, new = db.create_level(f"t{n}", {}, prepared=prepared, token=token, tags=["load"])
                    token = token or new
                    with lock:
                        created.append(level_id)
                elif action < 0.6 and token:
                    value = rng.choice((-1, 0, 1))
                    db.record_play(target, "human", solved=False, steps=1, seconds=0.1, author=token)  # may vote
                    db.vote(target, token, value)
                    with lock:
                        votes[(target, token)] = value
                        plays[(target, "human", False)] += 1
                else:
                    kind = rng.choice(("human", "agent"))
                    solved = rng.random() < 0.5
                    db.record_play(target, kind, solved=solved, steps=rng.randrange(1000), seconds=rng.random())
                    with lock:
                        plays[(target, kind, solved)] += 1
        except BaseException as error:  # noqa: B036 - reported by the main thread
            errors.append(error)

    threads = [threading.Thread(target=worker, args=(n,)) for n in range(THREADS)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    stores[1].close()
    assert not errors, errors[:3]
    print(f"\n{store.dialect}: {len(created)} levels, {sum(plays.values())} plays, {len(votes)} vote keys")
    assert len(created) > THREADS and sum(plays.values()) > THREADS
    counts = store.counts()
    assert counts["levels"] == len(seed_ids) + len(created)
    assert counts["plays"] == sum(plays.values())
    assert counts["votes"] == sum(1 for v in votes.values() if v != 0)
    for level_id in seed_ids + created[:20]:
        stats = store.stats(level_id)
        assert stats["human_plays"] == plays[(level_id, "human", True)] + plays[(level_id, "human", False)]
        assert stats["agent_solved"] == plays[(level_id, "agent", True)]
        assert stats["votes_up"] == sum(1 for (lid, _), v in votes.items() if lid == level_id and v == 1)
        assert stats["votes_down"] == sum(1 for (lid, _), v in votes.items() if lid == level_id and v == -1)
    assert store.integrity_check() == []


WRITER = """
import sys
from server.gallery.checks import SavedLevel
from server.gallery.store import Store
store = Store(sys.argv[1], seed_dir=None)
prepared = SavedLevel("m", sys.stdin.read(), b"png")
token = None
n = 0
while True:
    level_id, new = store.create_level(f"w{n}", {}, prepared=prepared, token=token)
    token = token or new
    store.record_play(level_id, "human", solved=True, steps=n, seconds=1.0, author=token)
    store.vote(level_id, token, 1)
    n += 1
    print(level_id, flush=True)  # after the commits: this level and its play and vote are durable
"""


def test_sigkill_during_writes_leaves_consistent_database(tmp_path: Path):
    url = f"sqlite:///{tmp_path / 'gallery.sqlite3'}"
    Store(url, seed_dir=None).close()
    level_json = prepare_level(level_doc()).level_json
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    for _round in range(3):
        child = subprocess.Popen([sys.executable, "-c", WRITER, url], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                 env=env, text=True)
        child.stdin.write(level_json)
        child.stdin.close()
        confirmed = [child.stdout.readline().strip() for _ in range(30)]
        os.kill(child.pid, signal.SIGKILL)
        child.wait()
        store = Store(url, seed_dir=None)
        assert store.integrity_check() == []
        for level_id in confirmed:
            stats = store.stats(level_id)
            assert stats["plays"] == 1 and stats["votes_up"] == 1
        store.close()


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start_server(db: Path, port: int, *extra: str) -> subprocess.Popen:
    import urllib.request

    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    server = subprocess.Popen([sys.executable, "-m", "server.gallery.app", "--db", str(db), "--port", str(port),
                               "--no-seed", *extra], env=env)
    for _ in range(300):
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/api/levels", timeout=1)
            return server
        except OSError:
            time.sleep(0.1)
    server.kill()
    raise AssertionError("the gallery server did not start")


def test_http_server_killed_during_writes_keeps_every_answered_write(tmp_path: Path):
    import httpx

    db = tmp_path / "gallery.sqlite3"
    store = Store(f"sqlite:///{db}", seed_dir=None)
    fake = SavedLevel("m", json.dumps(level_doc()), b"png")  # no renderer needed: only plays are written
    level_id, _ = store.create_level("target", {}, prepared=fake)
    with store._write() as conn:  # voters: each answered up-vote is one new row (plays cannot be posted)
        voters = [store.new_author(conn)[1] for _ in range(2000)]
    for token in voters:  # each played it (a vote needs a server-run play of the level by that identity)
        store.record_play(level_id, "human", solved=False, steps=1, seconds=0.1, author=token)
    store.close()
    port = _free_port()
    server = _start_server(db, port, "--write-limit", "0")  # many writes from one address, on purpose
    answered: list[str] = []
    stop = threading.Event()

    def writer() -> None:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}") as http:
            while not stop.is_set() and voters:
                token = voters.pop()
                try:
                    r = http.post(f"/api/levels/{level_id}/vote", json={"value": 1},
                                  headers={"Authorization": f"Bearer {token}"})
                except httpx.HTTPError:
                    return  # the server is gone
                assert r.status_code == 200, r.text
                answered.append(token)

    threads = [threading.Thread(target=writer) for _ in range(8)]
    for t in threads:
        t.start()
    while len(answered) < 200:
        time.sleep(0.05)
    os.kill(server.pid, signal.SIGKILL)  # in the middle of writes
    server.wait()
    stop.set()
    for t in threads:
        t.join()
    store = Store(f"sqlite:///{db}", seed_dir=None)
    assert store.integrity_check() == []
    votes = store.stats(level_id)["votes_up"]
    assert votes >= len(answered)  # every answered write survived; at most the unanswered in-flight ones extra
    store.close()
    server = _start_server(db, port)  # a restart serves the same data
    try:
        assert httpx.get(f"http://127.0.0.1:{port}/api/levels/{level_id}/stats").json()["votes_up"] == votes
    finally:
        server.kill()
        server.wait()
