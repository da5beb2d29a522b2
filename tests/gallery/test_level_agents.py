"""Gallery migration 3 (level_agents) and server.gallery.agents.LevelAgents: an old gallery upgrades with its
data intact, specialists attach only with a real checkpoint inside the agents dir, and are listed newest first."""

from __future__ import annotations

import json
import shutil

import pytest
from sqlalchemy import create_engine, text

from server.gallery import migrations
from server.gallery.agents import LevelAgents
from server.gallery.checks import Forbidden, Invalid, NotFound, Unauthorized
from server.gallery.store import Store
from tests.gallery.conftest import level_doc


def _v2_database(url: str) -> None:
    engine = create_engine(url)
    with engine.begin() as conn:
        assert migrations.migrate(conn, target=2) == 2
        conn.execute(text("INSERT INTO levels VALUES ('old', 'old level', '', NULL, 1, 1, NULL, 'm', :doc, :png)"),
                     {"doc": json.dumps(level_doc()), "png": b"\x89PNG"})
        conn.execute(text("INSERT INTO plays (level_id, kind, solved, steps, seconds, created) "
                          "VALUES ('old', 'agent', TRUE, 10, 2.0, 1)"))
    with engine.connect() as conn:
        tables = conn.dialect.get_table_names(conn)
    assert "level_agents" not in tables  # really the schema before migration 3
    engine.dispose()


def _checkpoint(agents_dir, run: str) -> None:
    (agents_dir / run / "checkpoint").mkdir(parents=True)
    (agents_dir / run / "checkpoint" / "config.json").write_text("{}")


def test_a_version_2_gallery_upgrades_to_3_and_keeps_its_data(db_url, tmp_path):
    _v2_database(db_url)
    store = Store(db_url, seed_dir=None, recordings_dir=tmp_path / "recordings")
    assert store.schema_version == migrations.LATEST >= 3
    assert store.get_level("old")["stats"]["agent_solved"] == 1
    agents = LevelAgents(store, tmp_path / "agents")
    _checkpoint(tmp_path / "agents", "run-1")
    _checkpoint(tmp_path / "agents", "run-2")
    # The old level has no author: only an admin (server-side tool) attaches to it.
    first = agents.attach("old", "run-1", token=None, admin=True, steps=2048, solve_rate=0.5, mean_return=0.1)
    second = agents.attach("old", "run-2", token=None, admin=True, steps=4096, name="better")
    listed = agents.list("old")
    assert [row["id"] for row in listed] == [second, first], "newest first"
    assert listed[0]["name"] == "better" and listed[0]["steps"] == 4096 and listed[0]["solve_rate"] is None
    assert listed[1]["path"] == tmp_path / "agents" / "run-1" / "checkpoint"
    store.delete_level("old", None, admin=True)  # a deleted level takes its specialists' rows with it
    assert agents.list("old") == []
    store.close()


def test_attach_refuses_bad_runs_and_lists_only_existing_checkpoints(store, tmp_path):
    level_id, token = store.create_level("level", level_doc())
    agents = LevelAgents(store, tmp_path / "agents")
    with pytest.raises(Invalid, match="no checkpoint"):
        agents.attach(level_id, "missing", token=token, steps=1)
    for bad in ("../escape", "a/b", "", ".hidden"):
        with pytest.raises(Invalid, match="plain directory name"):
            agents.attach(level_id, bad, token=token, steps=1)
    _checkpoint(tmp_path / "agents", "run")
    with pytest.raises(NotFound):
        agents.attach("nolevel", "run", token=token, steps=1)
    agents.attach(level_id, "run", token=token, steps=1)
    assert len(agents.list(level_id)) == 1
    (tmp_path / "agents" / "run" / "checkpoint" / "config.json").unlink()
    (tmp_path / "agents" / "run" / "checkpoint").rmdir()
    if store.dialect != "sqlite":  # several processes: the shared copy brings a lost folder back ...
        assert [row["path"].is_dir() for row in agents.list(level_id)] == [True]
        shutil.rmtree(tmp_path / "agents" / "run" / "checkpoint")
        with store._write() as conn:  # ... unless it is gone too
            conn.execute(text("DELETE FROM agent_checkpoints"))
    assert agents.list(level_id) == [], "a row whose checkpoint is gone is not offered"


def test_only_the_levels_author_can_attach_an_agent(store, tmp_path):
    level_id, author = store.create_level("mine", level_doc())
    _, stranger = store.create_level("theirs", level_doc())  # another author, known to the gallery
    agents = LevelAgents(store, tmp_path / "agents")
    _checkpoint(tmp_path / "agents", "run")
    for token, error, says in ((None, Unauthorized, "needs the author's token"),
                               ("not-a-token", Unauthorized, "unknown author token"),
                               (stranger, Forbidden, "does not own it")):
        with pytest.raises(error, match=says):
            agents.attach(level_id, "run", token=token, steps=1)
    assert agents.list(level_id) == [], "a refused attach leaves no row"
    assert not agents.owns(level_id, stranger) and not agents.owns(level_id, None)
    assert agents.owns(level_id, author) and not agents.owns("nolevel", author)
    agents.attach(level_id, "run", token=author, steps=1)
    assert [row["steps"] for row in agents.list(level_id)] == [1]
    agents.attach(level_id, "run", token=None, admin=True, steps=2)  # the admin (server-side tools) may
    assert len(agents.list(level_id)) == 2


def test_a_specialist_attached_on_one_process_is_offered_by_another_on_postgresql(db_url, tmp_path):
    """Two stores (two processes, each its own agents dir): on PostgreSQL B fetches A's checkpoint from the table
    agent_checkpoints; with SQLite the folder is the only copy, as before (one process)."""
    first, second = Store(db_url, seed_dir=None), Store(db_url, seed_dir=None)
    try:
        level_id, token = first.create_level("level", level_doc())
        a, b = LevelAgents(first, tmp_path / "a"), LevelAgents(second, tmp_path / "b")
        _checkpoint(tmp_path / "a", "run-1")
        (tmp_path / "a" / "run-1" / "checkpoint" / "params.msgpack").write_bytes(bytes(range(256)) * 8)
        agent_id = a.attach(level_id, "run-1", token=token, steps=100)
        listed = b.list(level_id)
        if first.dialect == "sqlite":
            assert listed == [] and b.remove_orphans() == 0
            return
        assert [row["id"] for row in listed] == [agent_id]
        fetched = tmp_path / "b" / "run-1" / "checkpoint"
        assert listed[0]["path"] == fetched
        assert (fetched / "params.msgpack").read_bytes() == bytes(range(256)) * 8
        assert (fetched / "config.json").read_text() == "{}"
        assert b.remove_orphans() == 0, "a stored checkpoint a specialist names stays"
        first.delete_level(level_id, token)
        assert b.remove_orphans() == 1, "its level deleted, nothing names it any more"
    finally:
        first.close()
        second.close()


def test_a_packed_checkpoint_is_checked_before_anything_is_written(tmp_path):
    import io
    import tarfile

    from server.gallery.checkpoints import CheckpointError, pack_checkpoint, unpack_checkpoint

    _checkpoint(tmp_path, "run")
    data = pack_checkpoint(tmp_path / "run" / "checkpoint")
    assert (unpack_checkpoint(data, tmp_path / "copy") / "config.json").read_text() == "{}"
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as archive:
        info = tarfile.TarInfo("../escape")
        info.size = 2
        archive.addfile(info, io.BytesIO(b"no"))
    for bad, why in ((buffer.getvalue(), "not a plain file"), (b"not a tar at all", "not a packed checkpoint")):
        with pytest.raises(CheckpointError, match=why):
            unpack_checkpoint(bad, tmp_path / "bad")
        assert not (tmp_path / "bad").exists() and not (tmp_path / "escape").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == [], "no partial folder left"
