"""Versioned schema migrations for the gallery database (SQLite and PostgreSQL).

The `schema_version` table holds one row per applied migration. `migrate` applies the missing ones in
order, each in the caller's transaction, so an old gallery file opens in a newer server and a failed
migration leaves the database at its previous version. Migrations are frozen once released: change the
schema by appending a new one, never by editing an old one.

SQL is written once for both databases; the only differences are spelled as placeholders:
{blob} (BLOB / BYTEA) and {serial_pk} (an auto-numbered integer primary key).
"""

from __future__ import annotations

import time

from sqlalchemy import Connection, text

# (version, what it does, statements)
MIGRATIONS: list[tuple[int, str, list[str]]] = [
    (1, "levels, authors, tags, votes and plays", [
        "CREATE TABLE meta (key VARCHAR(64) PRIMARY KEY, value TEXT NOT NULL)",
        "CREATE TABLE authors (id VARCHAR(16) PRIMARY KEY, token_hash CHAR(64) NOT NULL UNIQUE, "
        "created BIGINT NOT NULL)",
        """CREATE TABLE levels (
            id VARCHAR(32) PRIMARY KEY,
            name VARCHAR(100) NOT NULL,
            description TEXT NOT NULL,
            author_id VARCHAR(16) REFERENCES authors(id),
            created BIGINT NOT NULL,
            updated BIGINT NOT NULL,
            parent_id VARCHAR(32) REFERENCES levels(id) ON DELETE SET NULL,
            size VARCHAR(8) NOT NULL,
            level_json TEXT NOT NULL,
            thumbnail {blob} NOT NULL)""",
        "CREATE INDEX levels_created ON levels (created)",
        """CREATE TABLE level_tags (
            level_id VARCHAR(32) NOT NULL REFERENCES levels(id) ON DELETE CASCADE,
            tag VARCHAR(32) NOT NULL,
            PRIMARY KEY (level_id, tag))""",
        """CREATE TABLE votes (
            level_id VARCHAR(32) NOT NULL REFERENCES levels(id) ON DELETE CASCADE,
            author_id VARCHAR(16) NOT NULL REFERENCES authors(id),
            value SMALLINT NOT NULL,
            created BIGINT NOT NULL,
            PRIMARY KEY (level_id, author_id))""",
        """CREATE TABLE plays (
            id {serial_pk},
            level_id VARCHAR(32) NOT NULL REFERENCES levels(id) ON DELETE CASCADE,
            kind VARCHAR(8) NOT NULL,
            solved BOOLEAN NOT NULL,
            steps INTEGER NOT NULL,
            seconds DOUBLE PRECISION NOT NULL,
            created BIGINT NOT NULL)""",
    ]),
    (2, "play recordings (inline bytes or a file under recordings/) and an index for per-level stats", [
        "ALTER TABLE plays ADD COLUMN recording {blob}",
        "ALTER TABLE plays ADD COLUMN recording_path VARCHAR(255)",
        "CREATE INDEX plays_level ON plays (level_id, kind)",
        "CREATE INDEX level_tags_tag ON level_tags (tag)",
    ]),
    (3, "specialist agents trained on a level (checkpoint directories under <data dir>/agents/)", [
        """CREATE TABLE level_agents (
            id {serial_pk},
            level_id VARCHAR(32) NOT NULL REFERENCES levels(id) ON DELETE CASCADE,
            name VARCHAR(64) NOT NULL,
            checkpoint VARCHAR(255) NOT NULL,
            steps INTEGER NOT NULL,
            solve_rate DOUBLE PRECISION,
            mean_return DOUBLE PRECISION,
            created BIGINT NOT NULL)""",
        "CREATE INDEX level_agents_level ON level_agents (level_id)",
    ]),
    (4, "shared state for several server processes: drafts, best-run recordings, rate-limit buckets", [
        """CREATE TABLE drafts (
            id VARCHAR(64) PRIMARY KEY,
            document {blob} NOT NULL,
            updated BIGINT NOT NULL)""",
        "CREATE INDEX drafts_updated ON drafts (updated)",
        """CREATE TABLE recording_files (
            name VARCHAR(255) PRIMARY KEY,
            data {blob} NOT NULL,
            created BIGINT NOT NULL)""",
        """CREATE TABLE rate_buckets (
            kind VARCHAR(16) NOT NULL,
            client VARCHAR(64) NOT NULL,
            tokens DOUBLE PRECISION NOT NULL,
            stamp DOUBLE PRECISION NOT NULL,
            PRIMARY KEY (kind, client))""",
        "CREATE INDEX rate_buckets_stamp ON rate_buckets (stamp)",
    ]),
    (5, "who played: a vote counts only from an identity that played the level in a server-run play", [
        "ALTER TABLE plays ADD COLUMN author_id VARCHAR(16) REFERENCES authors(id)",
        "CREATE INDEX plays_level_author ON plays (level_id, author_id)",
    ]),
    (6, "the browser's training queue shared by server processes, and specialists' checkpoints", [
        """CREATE TABLE training_jobs (
            id {serial_pk},
            client VARCHAR(80) NOT NULL,
            owner VARCHAR(64) NOT NULL,
            worker VARCHAR(64),
            state VARCHAR(12) NOT NULL,
            steps INTEGER NOT NULL,
            level_json TEXT NOT NULL,
            options TEXT NOT NULL,
            progress TEXT NOT NULL,
            progress_n INTEGER NOT NULL,
            result TEXT,
            error TEXT,
            checkpoint {blob},
            cancel BOOLEAN NOT NULL,
            created BIGINT NOT NULL,
            started BIGINT,
            heartbeat BIGINT,
            finished BIGINT)""",
        "CREATE INDEX training_jobs_state ON training_jobs (state, id)",
        "CREATE INDEX training_jobs_client ON training_jobs (client, started)",
        """CREATE TABLE training_workers (
            id VARCHAR(64) PRIMARY KEY,
            slots INTEGER NOT NULL,
            heartbeat BIGINT NOT NULL)""",
        """CREATE TABLE agent_checkpoints (
            name VARCHAR(255) PRIMARY KEY,
            data {blob} NOT NULL,
            created BIGINT NOT NULL)""",
    ]),
    (7, "recent recordings: each tab's last play, found again after a reload through any process", [
        """CREATE TABLE recent_recordings (
            tab VARCHAR(64) PRIMARY KEY,
            name VARCHAR(255) NOT NULL,
            player VARCHAR(100) NOT NULL,
            level_id VARCHAR(32),
            result VARCHAR(16) NOT NULL,
            steps INTEGER NOT NULL,
            seconds DOUBLE PRECISION NOT NULL,
            ended BIGINT NOT NULL,
            seen BIGINT NOT NULL,
            size_bytes BIGINT NOT NULL,
            data {blob} NOT NULL)""",
        "CREATE INDEX recent_recordings_seen ON recent_recordings (seen)",
    ]),
]

LATEST = MIGRATIONS[-1][0]

_DIALECT_WORDS = {
    "sqlite": {"blob": "BLOB", "serial_pk": "INTEGER PRIMARY KEY AUTOINCREMENT"},
    "postgresql": {"blob": "BYTEA", "serial_pk": "BIGINT GENERATED BY DEFAULT AS IDENTITY PRIMARY KEY"},
}
# Any constant: PostgreSQL processes starting at once take this lock so only one of them migrates.
_PG_MIGRATION_LOCK = 0x6B696E6574


def current_version(conn: Connection) -> int:
    """The applied schema version (0 for an empty database)."""
    dialect = conn.dialect.name
    if dialect == "sqlite":
        exists = conn.exec_driver_sql(
            "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'schema_version'").first()
    else:
        exists = conn.exec_driver_sql("SELECT to_regclass('schema_version')").scalar()
    if not exists:
        return 0
    return conn.execute(text("SELECT COALESCE(MAX(version), 0) FROM schema_version")).scalar_one()


def migrate(conn: Connection, target: int | None = None) -> int:
    """Bring the schema up to `target` (default: the latest) inside `conn`'s transaction; returns the version.

    Refuses a database newer than this code, rather than guessing what its extra columns mean.
    """
    dialect = conn.dialect.name
    if dialect not in _DIALECT_WORDS:
        raise RuntimeError(f"unsupported database {dialect!r}: use SQLite or PostgreSQL")
    if dialect == "postgresql":
        conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": _PG_MIGRATION_LOCK})
    target = LATEST if target is None else target
    version = current_version(conn)
    if version > LATEST:
        raise RuntimeError(f"the gallery database has schema version {version}, newer than this program "
                           f"understands ({LATEST}); upgrade the program")
    if version == 0:
        conn.exec_driver_sql("CREATE TABLE schema_version (version INTEGER PRIMARY KEY, applied BIGINT NOT NULL, "
                             "description TEXT NOT NULL)")
    words = _DIALECT_WORDS[dialect]
    for number, description, statements in MIGRATIONS:
        if version < number <= target:
            for statement in statements:
                conn.exec_driver_sql(statement.format(**words))
            conn.execute(text("INSERT INTO schema_version (version, applied, description) VALUES (:v, :t, :d)"),
                         {"v": number, "t": int(time.time() * 1000), "d": description})
            version = number
    return version
