"""The gallery page (no user text as HTML), migrations of an old database, seeding and restarts."""

from __future__ import annotations

import json
import re
import sqlite3

from sqlalchemy import create_engine, text

from server.gallery import migrations
from server.gallery.store import Store, open_store
from tests.gallery.conftest import level_doc

STATIC = __import__("pathlib").Path(__file__).resolve().parents[2] / "static"


def test_page_is_served_and_never_inserts_html(client):
    page = client.get("/gallery")
    assert page.status_code == 200 and "gallery.js" in page.text
    script = client.get("/static/gallery.js").text
    assert "textContent" in script
    # No HTML-parsing sinks anywhere in the page's script: user data can only become text.
    for sink in ("innerHTML", "outerHTML", "insertAdjacentHTML", "document.write", "eval("):
        assert sink not in script, sink
    assert "kinetix.author_token" in script
    assert client.get("/static/gallery.css").status_code == 200


def test_xss_name_is_stored_verbatim(client):
    name = "<img src=x onerror=alert(1)>"
    made = client.post("/api/levels", json={"name": name, "description": "<script>alert(2)</script>",
                                            "level": level_doc()}).json()
    level = client.get(f"/api/levels/{made['id']}")
    assert level.headers["content-type"].startswith("application/json")
    assert level.json()["name"] == name and level.json()["description"] == "<script>alert(2)</script>"
    # The static page contains no level data at all: cards are built client-side with textContent.
    assert "onerror" not in client.get("/gallery").text


def _v1_database(url: str) -> None:
    engine = create_engine(url)
    with engine.begin() as conn:
        assert migrations.migrate(conn, target=1) == 1
        conn.execute(text("INSERT INTO authors VALUES ('a1', 'h1', 1)"))
        conn.execute(text("INSERT INTO levels VALUES ('old', 'old level', '', 'a1', 1, 1, NULL, 'm', :doc, :png)"),
                     {"doc": json.dumps(level_doc()), "png": b"\x89PNG"})
        conn.execute(text("INSERT INTO plays (level_id, kind, solved, steps, seconds, created) "
                          "VALUES ('old', 'human', TRUE, 10, 2.0, 1)"))
        conn.execute(text("INSERT INTO votes VALUES ('old', 'a1', 1, 1)"))
        columns = conn.execute(text("SELECT * FROM plays")).keys()
    assert "recording_path" not in columns  # really the old schema
    engine.dispose()


def test_v1_database_opens_in_current_code(db_url, tmp_path):
    _v1_database(db_url)
    store = Store(db_url, seed_dir=None, recordings_dir=tmp_path / "recordings")
    assert store.schema_version == migrations.LATEST > 1
    level = store.get_level("old")
    assert level["name"] == "old level" and level["stats"]["human_solved"] == 1 and level["stats"]["score"] == 1
    assert store.thumbnail("old") == b"\x89PNG"
    play = store.record_play("old", "agent", solved=False, steps=3, seconds=0.1, recording_path="run1.mcap")
    assert store.recording_file(play) == tmp_path / "recordings" / "run1.mcap"
    with store.engine.connect() as conn:
        versions = [r[0] for r in conn.execute(text("SELECT version FROM schema_version ORDER BY 1"))]
    assert versions == [m[0] for m in migrations.MIGRATIONS]
    store.close()
    again = Store(db_url, seed_dir=None)  # reopening an up-to-date database changes nothing
    assert again.schema_version == migrations.LATEST and again.counts()["plays"] == 2
    again.close()


def test_newer_database_is_refused(tmp_path):
    path = tmp_path / "new.sqlite3"
    Store(f"sqlite:///{path}", seed_dir=None).close()
    with sqlite3.connect(path) as conn:
        conn.execute("INSERT INTO schema_version VALUES (999, 0, 'from the future')")
    try:
        Store(f"sqlite:///{path}", seed_dir=None)
    except RuntimeError as error:
        assert "newer" in str(error)
    else:
        raise AssertionError("a newer schema must be refused")


def test_seed_once_and_restart_keeps_everything(db_url, tmp_path):
    seeds = tmp_path / "seeds"
    seeds.mkdir()
    for name in ("car_right", "pinball"):
        (seeds / f"{name}.json").write_text(json.dumps(level_doc(name)))
    store = Store(db_url, seed_dir=seeds)
    assert store.counts()["levels"] == 2
    assert {i["id"] for i in store.list_levels()[0]} == {"car-right", "pinball"}
    store.delete_level("pinball", None, admin=True)
    level_id, token = store.create_level("mine", level_doc(), tags=["x"])
    store.record_play(level_id, "human", solved=True, steps=5, seconds=1.0, author=token)
    store.vote(level_id, token, 1)
    before = store.counts()
    store.close()
    again = Store(db_url, seed_dir=seeds)  # a restart: no re-seeding, the deleted seed stays deleted
    assert again.counts() == before and again.seed(seeds) == 0
    assert again.get_level(level_id)["stats"]["score"] == 1 and again.author_of(token)
    assert again.integrity_check() == []
    again.close()


def test_open_store_default_path_and_env(tmp_path, monkeypatch):
    monkeypatch.delenv("KINETIX_DB", raising=False)
    store = open_store(data_dir=tmp_path / "data", seed_dir=None)
    assert (tmp_path / "data" / "gallery.sqlite3").exists()
    mode = store.engine.connect().exec_driver_sql("PRAGMA journal_mode").scalar()
    assert mode == "wal"
    store.close()
    monkeypatch.setenv("KINETIX_DB", str(tmp_path / "env.sqlite3"))
    open_store(seed_dir=None).close()
    assert (tmp_path / "env.sqlite3").exists()
    assert re.match(r"postgresql\+psycopg://", __import__("server.gallery.schema", fromlist=["x"]).resolve_db_url(
        "postgresql://u@h/db"))


def _open_two_at_once(url: str, seed_dir) -> tuple[list[Store], list[BaseException]]:
    """Two stores (as two server processes would) opening `url` at the same moment: (opened, errors)."""
    import threading

    opened, errors = [], []
    barrier = threading.Barrier(2)

    def start() -> None:
        try:
            barrier.wait()
            opened.append(Store(url, seed_dir=seed_dir))
        except BaseException as error:  # noqa: B036 - reported by the callers
            errors.append(error)

    threads = [threading.Thread(target=start) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return opened, errors


def test_two_processes_starting_at_once_migrate_and_seed_once(db_url):
    """Two stores (as two server processes would) opening an empty gallery at the same moment."""
    from server.gallery.store import REPO_LEVELS

    opened, errors = _open_two_at_once(db_url, REPO_LEVELS)
    assert not errors, errors
    project = sorted(REPO_LEVELS.glob("*.json"))
    assert opened[0].counts()["levels"] == len(project) > 0
    items, _ = opened[0].list_levels(tag="project", limit=100)
    assert {i["id"] for i in items} == {p.stem.replace("_", "-") for p in project}
    assert all(opened[0].thumbnail(i["id"])[:4] == b"\x89PNG" for i in items)
    for store in opened:
        store.close()


def test_new_sqlite_galleries_opened_by_two_stores_at_once_never_report_locked(tmp_path):
    """Switching a new file to WAL needs an exclusive lock, and SQLite answers "database is locked" at once
    (no busy wait) to the loser of that race: about one race in five failed before schema._enter_wal."""
    for attempt in range(20):
        opened, errors = _open_two_at_once(f"sqlite:///{tmp_path / f'race{attempt}.sqlite3'}", None)
        assert not errors, (attempt, errors)
        assert [s.schema_version for s in opened] == [opened[0].schema_version] * 2
        for store in opened:
            store.close()
