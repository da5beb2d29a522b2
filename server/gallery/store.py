"""The gallery's storage: one layer for SQLite (the default, one WAL file) and PostgreSQL (shared by processes).

    store = open_store()                                   # KINETIX_DB, else <data dir>/gallery.sqlite3
    store = open_store("postgresql://user@host/db")        # several server processes share one gallery
    level_id, token = store.create_level("my car", level_doc)     # a new author token when none is given
    store.record_play(level_id, "human", solved=True, steps=120, seconds=4.2)
    store.vote(level_id, token, +1)

Written with SQLAlchemy Core: it gives one SQL dialect layer, connection pooling for threads and psycopg 3
for PostgreSQL, while queries stay plain SQL expressions. Every public call is one transaction; on SQLite
writes start with BEGIN IMMEDIATE so concurrent writers queue on the busy timeout instead of failing
with "database is locked" when a read transaction tries to upgrade.

Errors: StoreError subclasses carry a user-facing message; NotFound (unknown id), Unauthorized (missing or
unknown token), Forbidden (a token that does not own the level), Invalid (bad input). Nothing is written
when any of them is raised.
"""

from __future__ import annotations

import json
import math
import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sqlalchemy import (
    Connection,
    and_,
    create_engine,
    func,
    or_,
    select,
    text,
)
from sqlalchemy.engine import make_url
from sqlalchemy.exc import IntegrityError

from server.gallery import migrations, queries
from server.gallery.checks import (
    KINDS,
    MAX_NAME,
    RECORDING_RE,
    SIZES,
    SORTS,
    Forbidden,
    Invalid,
    NotFound,
    SavedLevel,
    Unauthorized,
    check_description,
    check_id,
    check_name,
    check_tags,
    check_unicode,
    prepare_level,
)
from server.gallery.schema import (
    _sqlite_engine,
    author_id_for,
    authors_t,
    default_data_dir,
    levels_t,
    meta_t,
    now_ms,
    plays_t,
    resolve_db_url,
    tags_t,
    token_hash,
    votes_t,
)

REPO_LEVELS = Path(__file__).resolve().parents[2] / "levels"
NOT_PLAYED = ("only someone who played this level may vote on it: play it in the browser (its Play link), then "
              "vote from the same browser")


class Store:
    """The gallery database. Thread-safe; create one per process and share it."""

    def __init__(self, url: str, *, seed_dir: str | os.PathLike | None = REPO_LEVELS,
                 recordings_dir: str | os.PathLike | None = None):
        self.url = url
        self.dialect = make_url(url).get_backend_name()
        if self.dialect == "sqlite":
            self.engine = _sqlite_engine(url)
        elif self.dialect == "postgresql":
            self.engine = create_engine(url, pool_size=20, max_overflow=20, pool_pre_ping=True)
        else:
            raise ValueError(f"unsupported database {self.dialect!r}: use SQLite or PostgreSQL")
        self._writer = self.engine.execution_options(write=True)
        if recordings_dir is None and self.dialect == "sqlite" and make_url(url).database:
            recordings_dir = Path(make_url(url).database).parent / "recordings"
        self.recordings_dir = Path(recordings_dir) if recordings_dir is not None else None
        with self._writer.begin() as conn:
            self.schema_version = migrations.migrate(conn)
        if seed_dir is not None:
            self.seed(seed_dir)

    def close(self) -> None:
        self.engine.dispose()

    @contextmanager
    def _write(self) -> Iterator[Connection]:
        with self._writer.begin() as conn:
            yield conn

    @contextmanager
    def _read(self) -> Iterator[Connection]:
        with self.engine.begin() as conn:
            yield conn

    # ---- authors ----
    def new_author(self, conn: Connection) -> tuple[str, str]:
        token = secrets.token_urlsafe(32)
        author = author_id_for(token)
        conn.execute(authors_t.insert().values(id=author, token_hash=token_hash(token), created=now_ms()))
        return author, token

    def _author(self, conn: Connection, token: str) -> str:
        row = conn.execute(select(authors_t.c.id).where(authors_t.c.token_hash == token_hash(token))).first()
        if row is None:
            raise Unauthorized("unknown author token; send none to be issued a new one")
        return row.id

    def author_of(self, token: str) -> str:
        with self._read() as conn:
            return self._author(conn, token)

    def identity(self, token: str | None) -> tuple[str, bool]:
        """(a token this gallery knows, whether it is new): `token` itself when it is known, else a new identity.
        A tab keeps one identity for its saves and plays (server.play.gallery_tab)."""
        if token:
            with self._read() as conn:
                if conn.execute(select(authors_t.c.id).where(authors_t.c.token_hash == token_hash(token))).first():
                    return token, False
        with self._write() as conn:
            return self.new_author(conn)[1], True

    # ---- levels ----
    def create_level(self, name: str, level: dict, *, description: str = "", tags: list[str] | None = None,
                     token: str | None = None, parent: str | None = None,
                     prepared: SavedLevel | None = None) -> tuple[str, str | None]:
        """Save a new level; returns (id, new author token or None when `token` was given).

        `level` is a parsed document in either format; `parent` is the id of the level this remixes.
        """
        name, description = check_name(name), check_description(description)
        tags = check_tags(tags if tags is not None else [])
        if parent is not None and not isinstance(parent, str):
            raise Invalid("parent: expected a level id string or null")
        if parent is not None:
            check_unicode("parent", parent)
        saved = prepared or prepare_level(level, name)
        level_id = secrets.token_urlsafe(9)
        with self._write() as conn:
            new_token = None
            if token is None:
                author, new_token = self.new_author(conn)
            else:
                author = self._author(conn, token)
            if parent is not None and conn.execute(
                    select(levels_t.c.id).where(levels_t.c.id == parent)).first() is None:
                raise Invalid(f"parent: no level with id {parent[:40]!r}")
            stamp = now_ms()
            conn.execute(levels_t.insert().values(
                id=level_id, name=name, description=description, author_id=author, created=stamp, updated=stamp,
                parent_id=parent, size=saved.size, level_json=saved.level_json, thumbnail=saved.thumbnail))
            if tags:
                conn.execute(tags_t.insert(), [{"level_id": level_id, "tag": tag} for tag in tags])
        return level_id, new_token

    def _check_owner(self, conn: Connection, level_id: str, token: str | None, admin: bool) -> None:
        row = conn.execute(select(levels_t.c.author_id).where(levels_t.c.id == level_id)).first()
        if row is None:
            raise NotFound(f"no level with id {level_id!r}")
        if admin:
            return
        if not token:
            raise Unauthorized("this needs the author's token: send Authorization: Bearer TOKEN")
        if self._author(conn, token) != row.author_id:
            raise Forbidden("this token does not own this level")

    def update_level(self, level_id: str, token: str | None, *, admin: bool = False, name: str | None = None,
                     description: str | None = None, tags: list[str] | None = None,
                     level: dict | None = None) -> None:
        """Change the given fields of a level (author or admin only); the thumbnail follows the level."""
        check_id(level_id)
        values: dict[str, Any] = {}
        if name is not None:
            values["name"] = check_name(name)
        if description is not None:
            values["description"] = check_description(description)
        tags = check_tags(tags) if tags is not None else None
        if level is not None:
            saved = prepare_level(level, name)
            values.update(size=saved.size, level_json=saved.level_json, thumbnail=saved.thumbnail)
        with self._write() as conn:
            self._check_owner(conn, level_id, token, admin)
            values["updated"] = now_ms()
            conn.execute(levels_t.update().where(levels_t.c.id == level_id).values(**values))
            if tags is not None:
                conn.execute(tags_t.delete().where(tags_t.c.level_id == level_id))
                if tags:
                    conn.execute(tags_t.insert(), [{"level_id": level_id, "tag": tag} for tag in tags])

    def delete_level(self, level_id: str, token: str | None, *, admin: bool = False) -> None:
        check_id(level_id)
        with self._write() as conn:
            self._check_owner(conn, level_id, token, admin)
            conn.execute(levels_t.delete().where(levels_t.c.id == level_id))

    # ---- votes and plays ----
    def vote(self, level_id: str, token: str | None, value: int) -> dict:
        """Set this identity's vote on a level (+1, -1, or 0 to withdraw); one vote per identity per level.

        Only an identity that played the level as a human in a play the server ran (`record_play(author=...)`)
        may vote +1 or -1: a vote costs a real play, so new identities (cookie-less requests, scripts) add
        nothing. Returns the level's vote counts.
        """
        check_id(level_id)
        if value not in (-1, 0, 1) or isinstance(value, bool):
            raise Invalid("value: expected 1 (up), -1 (down) or 0 (withdraw)")
        if not token:
            raise Forbidden(NOT_PLAYED)
        with self._write() as conn:
            author = self._author(conn, token)
            if conn.execute(select(levels_t.c.id).where(levels_t.c.id == level_id)).first() is None:
                raise NotFound(f"no level with id {level_id!r}")
            if value == 0:
                conn.execute(votes_t.delete().where(and_(votes_t.c.level_id == level_id,
                                                         votes_t.c.author_id == author)))
            else:
                if conn.execute(select(plays_t.c.id).where(
                        plays_t.c.level_id == level_id, plays_t.c.author_id == author,
                        plays_t.c.kind == "human").limit(1)).first() is None:
                    raise Forbidden(NOT_PLAYED)
                # One statement that is atomic on both databases: no read-then-write race between voters.
                conn.execute(text(
                    "INSERT INTO votes (level_id, author_id, value, created) VALUES (:l, :a, :v, :t) "
                    "ON CONFLICT (level_id, author_id) DO UPDATE SET value = excluded.value"),
                    {"l": level_id, "a": author, "v": value, "t": now_ms()})
            up, down = self._vote_counts(conn, level_id)
        return {"up": up, "down": down, "score": up - down, "value": value}

    def _vote_counts(self, conn: Connection, level_id: str) -> tuple[int, int]:
        row = conn.execute(select(func.count().filter(votes_t.c.value > 0), func.count().filter(votes_t.c.value < 0))
                           .where(votes_t.c.level_id == level_id)).one()
        return int(row[0]), int(row[1])

    def record_play(self, level_id: str, kind: str, *, solved: bool, steps: int, seconds: float,
                    recording: bytes | None = None, recording_path: str | None = None,
                    author: str | None = None) -> int:
        """Record one finished play; returns its id. `author`: the token of the identity that played (the tab's;
        an unknown one records no player), which may then vote on the level.

        `recording_path` is a file name inside the recordings directory (no folders, no '..'): the server
        writes the MCAP there and stores only its name, so no request can point the gallery elsewhere.
        """
        check_id(level_id)
        if kind not in KINDS:
            raise Invalid(f"kind: expected one of {', '.join(KINDS)}, got {kind!r}")
        if not isinstance(solved, bool):
            raise Invalid("solved: expected true or false")
        if not isinstance(steps, int) or isinstance(steps, bool) or not 0 <= steps <= 10_000_000:
            raise Invalid("steps: expected an integer from 0 to 10000000")
        if (not isinstance(seconds, (int, float)) or isinstance(seconds, bool) or not math.isfinite(seconds)
                or not 0 <= seconds <= 1e7):
            raise Invalid("seconds: expected a number from 0 to 1e7")
        if recording_path is not None and (not isinstance(recording_path, str) or not RECORDING_RE.match(recording_path)
                                           or ".." in recording_path):
            raise Invalid("recording_path: expected a plain file name inside the recordings directory")
        if recording is not None and not isinstance(recording, (bytes, bytearray)):
            raise Invalid("recording: expected bytes")
        with self._write() as conn:
            player = None
            if author:
                row = conn.execute(select(authors_t.c.id).where(authors_t.c.token_hash == token_hash(author))).first()
                player = row.id if row is not None else None
            try:
                result = conn.execute(plays_t.insert().values(
                    level_id=level_id, kind=kind, solved=solved, steps=steps, seconds=float(seconds),
                    created=now_ms(), recording=recording, recording_path=recording_path,
                    author_id=player).returning(plays_t.c.id))
                return int(result.scalar_one())
            except IntegrityError:
                raise NotFound(f"no level with id {level_id!r}") from None

    def recording_file(self, play_id: int) -> Path | None:
        """The recording file of a play, if it has one inside the recordings directory."""
        with self._read() as conn:
            row = conn.execute(select(plays_t.c.recording_path).where(plays_t.c.id == play_id)).first()
        if row is None or row.recording_path is None or self.recordings_dir is None:
            return None
        return self.recordings_dir / row.recording_path

    # ---- reading ----
    def list_levels(self, *, sort: str = "newest", size: str | None = None, tag: str | None = None,
                    q: str | None = None, author: str | None = None, limit: int = 24,
                    cursor: str | None = None) -> tuple[list[dict], str | None]:
        """One page of level summaries and the cursor of the next page (None at the end)."""
        if sort not in SORTS:
            raise Invalid(f"sort: expected one of {', '.join(SORTS)}, got {sort!r}")
        if size is not None and size not in SIZES:
            raise Invalid(f"size: expected one of {', '.join(SIZES)}, got {size!r}")
        if not 1 <= limit <= 100:
            raise Invalid("limit: expected 1 to 100")
        for field, value in (("tag", tag), ("q", q), ("author", author)):
            if value is not None:  # NUL matched every name on SQLite (C strings end there) and fails on PostgreSQL
                check_unicode(field, value)
        query, keys = queries.listing()
        key = keys[sort]
        query = query.add_columns(key.label("sort_key"))
        ascending = sort == "hardest"
        if size is not None:
            query = query.where(levels_t.c.size == size)
        if tag:
            query = query.where(levels_t.c.id.in_(select(tags_t.c.level_id).where(tags_t.c.tag == tag.lower())))
        if q:
            query = query.where(func.lower(levels_t.c.name).contains(q.lower(), autoescape=True))
        if author:
            query = query.where(levels_t.c.author_id == author)
        if cursor:
            last_key, last_id = queries.decode_cursor(cursor)
            if ascending:
                query = query.where(or_(key > last_key, and_(key == last_key, levels_t.c.id > last_id)))
            else:
                query = query.where(or_(key < last_key, and_(key == last_key, levels_t.c.id < last_id)))
        order = (key.asc(), levels_t.c.id.asc()) if ascending else (key.desc(), levels_t.c.id.desc())
        with self._read() as conn:
            rows = conn.execute(query.order_by(*order).limit(limit + 1)).all()
            page = rows[:limit]
            tags = queries.tags_of(conn, [r.id for r in page])
        items = [queries.summary(r, tags[r.id]) for r in page]
        nxt = queries.encode_cursor(int(page[-1].sort_key), page[-1].id) if len(rows) > limit else None
        return items, nxt

    def get_level(self, level_id: str) -> dict:
        """Metadata, stats and the level document (our format) of one level."""
        check_id(level_id)
        query, _ = queries.listing(level_id)
        with self._read() as conn:
            row = conn.execute(query.add_columns(levels_t.c.level_json).where(levels_t.c.id == level_id)).first()
            if row is None:
                raise NotFound(f"no level with id {level_id!r}")
            out = queries.summary(row, queries.tags_of(conn, [level_id])[level_id])
        out["level"] = json.loads(row.level_json)
        return out

    def stats(self, level_id: str) -> dict:
        check_id(level_id)
        query, _ = queries.listing(level_id)
        with self._read() as conn:
            row = conn.execute(query.where(levels_t.c.id == level_id)).first()
        if row is None:
            raise NotFound(f"no level with id {level_id!r}")
        return queries.summary(row, [])["stats"]

    def thumbnail(self, level_id: str) -> bytes:
        check_id(level_id)
        with self._read() as conn:
            row = conn.execute(select(levels_t.c.thumbnail).where(levels_t.c.id == level_id)).first()
        if row is None:
            raise NotFound(f"no level with id {level_id!r}")
        return bytes(row.thumbnail)

    def counts(self) -> dict[str, int]:
        """Row counts per table (for tests and the admin)."""
        with self._read() as conn:
            return {t.name: int(conn.execute(select(func.count()).select_from(t)).scalar_one())
                    for t in (levels_t, authors_t, tags_t, votes_t, plays_t)}

    # ---- seeding ----
    def seed(self, folder: str | os.PathLike) -> int:
        """Add every level file of `folder` on the first start only; returns how many were added.

        A 'seeded' row in meta marks it done, inserted in the same transaction as the levels: seeding happens
        exactly once even when several processes start at once, and levels deleted later stay deleted.
        """
        with self._read() as conn:
            if conn.execute(select(meta_t.c.key).where(meta_t.c.key == "seeded")).first() is not None:
                return 0
        prepared = []
        for path in sorted(Path(folder).glob("*.json")):
            doc = json.loads(path.read_text(encoding="utf-8"))
            name = (doc.get("name") or path.stem)[:MAX_NAME]
            prepared.append((path.stem, name, prepare_level(doc, name)))
        with self._write() as conn:
            inserted = conn.execute(text(
                "INSERT INTO meta (key, value) VALUES ('seeded', :v) ON CONFLICT (key) DO NOTHING"),
                {"v": str(now_ms())}).rowcount
            if inserted != 1:
                return 0
            stamp = now_ms()
            for i, (stem, name, saved) in enumerate(prepared):
                level_id = stem.replace("_", "-")[:32]
                conn.execute(levels_t.insert().values(
                    id=level_id, name=name, description="", author_id=None, created=stamp - i, updated=stamp - i,
                    parent_id=None, size=saved.size, level_json=saved.level_json, thumbnail=saved.thumbnail))
                conn.execute(tags_t.insert().values(level_id=level_id, tag="project"))
        return len(prepared)

    def integrity_check(self) -> list[str]:
        """Problems found by the database's own check plus dangling references (an empty list when consistent)."""
        problems: list[str] = []
        with self._read() as conn:
            if self.dialect == "sqlite":
                problems += [r[0] for r in conn.exec_driver_sql("PRAGMA integrity_check") if r[0] != "ok"]
                problems += [str(tuple(r)) for r in conn.exec_driver_sql("PRAGMA foreign_key_check")]
            for table in (tags_t, votes_t, plays_t):
                dangling = conn.execute(select(func.count()).select_from(table).where(
                    table.c.level_id.not_in(select(levels_t.c.id)))).scalar_one()
                if dangling:
                    problems.append(f"{table.name}: {dangling} rows refer to missing levels")
        return problems


def open_store(db: str | os.PathLike | None = None, *, data_dir: str | os.PathLike | None = None,
               seed_dir: str | os.PathLike | None = REPO_LEVELS) -> Store:
    """The gallery for --db / KINETIX_DB or <data dir>/gallery.sqlite3, migrated and seeded."""
    url = resolve_db_url(db, data_dir)
    recordings = None
    if not url.startswith("sqlite:"):
        recordings = (Path(data_dir) if data_dir is not None else default_data_dir()) / "recordings"
    return Store(url, seed_dir=seed_dir, recordings_dir=recordings)
