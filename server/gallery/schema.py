"""The gallery's tables (created and changed by server.gallery.migrations, never by metadata.create_all) and how to
reach the database: the URL from --db / KINETIX_DB or the data folder, SQLite's engine settings, ids and tokens."""

from __future__ import annotations

import hashlib
import os
import sqlite3
import time
from pathlib import Path

from sqlalchemy import (
    BigInteger,
    Boolean,
    Column,
    Float,
    Integer,
    LargeBinary,
    MetaData,
    SmallInteger,
    String,
    Table,
    Text,
    create_engine,
    event,
)
from sqlalchemy.engine import Engine

# The current schema, for building queries (created by the migrations, never by metadata.create_all).
_meta = MetaData()
meta_t = Table("meta", _meta, Column("key", String(64), primary_key=True), Column("value", Text))
authors_t = Table("authors", _meta, Column("id", String(16), primary_key=True), Column("token_hash", String(64)),
                  Column("created", BigInteger))
levels_t = Table(
    "levels", _meta, Column("id", String(32), primary_key=True), Column("name", String(100)),
    Column("description", Text), Column("author_id", String(16)), Column("created", BigInteger),
    Column("updated", BigInteger), Column("parent_id", String(32)), Column("size", String(8)),
    Column("level_json", Text), Column("thumbnail", LargeBinary))
tags_t = Table("level_tags", _meta, Column("level_id", String(32)), Column("tag", String(32)))
votes_t = Table("votes", _meta, Column("level_id", String(32)), Column("author_id", String(16)),
                Column("value", SmallInteger), Column("created", BigInteger))
plays_t = Table("plays", _meta, Column("id", BigInteger, primary_key=True), Column("level_id", String(32)),
                Column("kind", String(8)), Column("solved", Boolean), Column("steps", Integer),
                Column("seconds", Float), Column("created", BigInteger), Column("recording", LargeBinary),
                Column("recording_path", String(255)), Column("author_id", String(16)))
# Shared state of several server processes on one PostgreSQL database (migration 4; docs/deploy.md).
drafts_t = Table("drafts", _meta, Column("id", String(64), primary_key=True), Column("document", LargeBinary),
                 Column("updated", BigInteger))
recording_files_t = Table("recording_files", _meta, Column("name", String(255), primary_key=True),
                          Column("data", LargeBinary), Column("created", BigInteger))
rate_buckets_t = Table("rate_buckets", _meta, Column("kind", String(16), primary_key=True),
                       Column("client", String(64), primary_key=True), Column("tokens", Float),
                       Column("stamp", Float))

# The browser's training queue (migration 6; server.agents.queue) and the specialists' checkpoints shared by processes.
training_jobs_t = Table(
    "training_jobs", _meta, Column("id", BigInteger, primary_key=True), Column("client", String(80)),
    Column("owner", String(64)), Column("worker", String(64)), Column("state", String(12)), Column("steps", Integer),
    Column("level_json", Text), Column("options", Text), Column("progress", Text), Column("progress_n", Integer),
    Column("result", Text), Column("error", Text), Column("checkpoint", LargeBinary), Column("cancel", Boolean),
    Column("created", BigInteger), Column("started", BigInteger), Column("heartbeat", BigInteger),
    Column("finished", BigInteger))
training_workers_t = Table("training_workers", _meta, Column("id", String(64), primary_key=True),
                           Column("slots", Integer), Column("heartbeat", BigInteger))
agent_checkpoints_t = Table("agent_checkpoints", _meta, Column("name", String(255), primary_key=True),
                            Column("data", LargeBinary), Column("created", BigInteger))
# Each tab's last play (migration 7; server.recordings.recent).
recent_recordings_t = Table(
    "recent_recordings", _meta, Column("tab", String(64), primary_key=True), Column("name", String(255)),
    Column("player", String(100)), Column("level_id", String(32)), Column("result", String(16)),
    Column("steps", Integer), Column("seconds", Float), Column("ended", BigInteger), Column("seen", BigInteger),
    Column("size_bytes", BigInteger), Column("data", LargeBinary))


def now_ms() -> int:
    return int(time.time() * 1000)


def token_hash(token: str) -> str:
    return hashlib.sha256(("kinetix-token:" + token).encode()).hexdigest()


def author_id_for(token: str) -> str:
    """The public id shown for an author: derived from the token in another domain, so it reveals nothing."""
    return hashlib.sha256(("kinetix-author:" + token).encode()).hexdigest()[:12]


def default_data_dir() -> Path:
    if os.environ.get("KINETIX_DATA"):
        return Path(os.environ["KINETIX_DATA"])
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "kinetix"


def resolve_db_url(db: str | os.PathLike | None = None, data_dir: str | os.PathLike | None = None) -> str:
    """The SQLAlchemy URL for --db / KINETIX_DB (a postgresql:// URL, a sqlite:/// URL or a file path)
    or, when neither is given, <data dir>/gallery.sqlite3."""
    db = db if db is not None else os.environ.get("KINETIX_DB") or None
    if db is None:
        folder = Path(data_dir) if data_dir is not None else default_data_dir()
        folder.mkdir(parents=True, exist_ok=True)
        return f"sqlite:///{(folder / 'gallery.sqlite3').resolve()}"
    db = str(db)
    for prefix in ("postgresql://", "postgres://"):
        if db.startswith(prefix):
            return "postgresql+psycopg://" + db[len(prefix):]
    if db.startswith(("postgresql+", "sqlite:")):
        return db
    if "://" in db:
        raise ValueError(f"unsupported database URL {db!r}: use postgresql://... or a SQLite file path")
    Path(db).expanduser().resolve().parent.mkdir(parents=True, exist_ok=True)
    return f"sqlite:///{Path(db).expanduser().resolve()}"


SQLITE_BUSY_SECONDS = 60  # how long a statement waits on another connection's lock before failing


def _enter_wal(cursor, deadline: float) -> None:
    """Switch the file to WAL (persistent: done once per file, a no-op after).

    Switching needs an exclusive lock, and SQLite answers "database is locked" at once instead of calling the
    busy handler when another connection holds one, as when two processes open a new gallery at the same
    moment (measured: 18 of 100 such races failed). So wait here, as the busy timeout would.
    """
    while True:
        try:
            if cursor.execute("PRAGMA journal_mode").fetchone()[0].lower() == "wal":
                return
            cursor.execute("PRAGMA journal_mode=WAL")
            return
        except sqlite3.OperationalError as error:
            if "locked" not in str(error) or time.monotonic() > deadline:
                raise
            time.sleep(0.01)


def _sqlite_engine(url: str) -> Engine:
    engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": SQLITE_BUSY_SECONDS},
                           pool_size=20, max_overflow=20)

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_conn, _record):
        dbapi_conn.isolation_level = None  # we issue BEGIN ourselves (below), so BEGIN IMMEDIATE is possible
        cursor = dbapi_conn.cursor()
        _enter_wal(cursor, time.monotonic() + SQLITE_BUSY_SECONDS)
        # NORMAL in WAL mode survives a killed process (the WAL is replayed); only power loss can drop the
        # last commits. FULL would fsync every commit.
        cursor.execute("PRAGMA synchronous=NORMAL")
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_SECONDS * 1000}")
        cursor.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn):
        conn.exec_driver_sql("BEGIN IMMEDIATE" if conn.get_execution_options().get("write") else "BEGIN")

    return engine
