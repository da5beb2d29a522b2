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

import base64
import dataclasses
import hashlib
import hmac
import json
import math
import os
import re
import secrets
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sqlalchemy import (
    BigInteger,
    Boolean,
    Column,
    Connection,
    Float,
    Integer,
    LargeBinary,
    MetaData,
    SmallInteger,
    String,
    Table,
    Text,
    and_,
    case,
    create_engine,
    event,
    func,
    or_,
    select,
    text,
)
from sqlalchemy.engine import Engine, make_url
from sqlalchemy.exc import IntegrityError

from server.gallery import migrations

REPO_LEVELS = Path(__file__).resolve().parents[2] / "levels"
SIZES = ("s", "m", "l", "xl")
KINDS = ("human", "agent")
SORTS = ("newest", "top", "played", "hardest")
MAX_NAME = 100
MAX_DESCRIPTION = 2000
MAX_TAGS = 10
TAG_RE = re.compile(r"^[a-z0-9][a-z0-9_-]{0,31}$")
THUMBNAIL_SIZE = 256
ID_RE = re.compile(r"[A-Za-z0-9_-]{1,32}")
RECORDING_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,200}$")  # a plain file name under recordings/


class StoreError(Exception):
    status = 400

    def __init__(self, message: str):
        super().__init__(message)
        self.message = message


class Invalid(StoreError):
    status = 422


class NotFound(StoreError):
    status = 404


class Unauthorized(StoreError):
    status = 401


class Forbidden(StoreError):
    status = 403


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
                Column("recording_path", String(255)))


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


def _sqlite_engine(url: str) -> Engine:
    engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 60},
                           pool_size=20, max_overflow=20)

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_conn, _record):
        dbapi_conn.isolation_level = None  # we issue BEGIN ourselves (below), so BEGIN IMMEDIATE is possible
        cursor = dbapi_conn.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")
        # NORMAL in WAL mode survives a killed process (the WAL is replayed); only power loss can drop the
        # last commits. FULL would fsync every commit.
        cursor.execute("PRAGMA synchronous=NORMAL")
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.execute("PRAGMA busy_timeout=60000")
        cursor.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn):
        conn.exec_driver_sql("BEGIN IMMEDIATE" if conn.get_execution_options().get("write") else "BEGIN")

    return engine


@dataclasses.dataclass
class SavedLevel:
    """What a save produces before it touches the database: validated fields and the rendered thumbnail."""

    size: str
    level_json: str
    thumbnail: bytes


def prepare_level(level: Any, name: str | None = None) -> SavedLevel:
    """Validate a level document (either format, as a parsed dict) and render its thumbnail.

    Raises Invalid with the loader's message; the gallery holds levels of size s, m or l only, the classes
    the play server compiles for.
    """
    from kinetix.level import LevelError
    from kinetix.levels import dumps, load_level
    from kinetix.render import render_thumbnail_png

    if not isinstance(level, dict):
        raise Invalid(f"level: expected a JSON object in our format or the Kinetix format, got {_json_type(level)}")
    check_document_text("level", level)
    try:
        file = load_level(level)
    except LevelError as error:
        raise Invalid(f"level: {error}") from None
    except RecursionError:
        raise Invalid("level: nested too deeply") from None
    if file.size.name not in SIZES:
        raise Invalid(f"level: size {file.size.name!r} is not a gallery size class; use s, m, l or xl")
    if name is not None:
        file = dataclasses.replace(file, name=name)
    return SavedLevel(file.size.name, dumps(file, "ours"), render_thumbnail_png(file.level, THUMBNAIL_SIZE))


def _json_type(value: Any) -> str:
    return {dict: "object", list: "array", str: "string", bool: "boolean", int: "number", float: "number",
            type(None): "null"}.get(type(value), type(value).__name__)


def check_unicode(field: str, text: str) -> str:
    """`text` unchanged if both databases can store it: no lone UTF-16 surrogates (JSON's "\\ud800" decodes to
    one, and neither UTF-8 nor PostgreSQL can hold it) and no NUL (PostgreSQL text cannot hold it)."""
    if "\x00" in text:
        raise Invalid(f"{field}: must not contain NUL characters")
    try:
        text.encode("utf-8")
    except UnicodeEncodeError as error:
        raise Invalid(f"{field}: contains a lone UTF-16 surrogate ({text[error.start]!r} at character "
                      f"{error.start}); text must be valid Unicode") from None
    return text


def check_document_text(field: str, value: Any, depth: int = 0) -> None:
    """Every string (keys too) of a parsed JSON document is valid Unicode; the error names the path."""
    if depth > 64:
        raise Invalid(f"{field}: nested too deeply")
    if isinstance(value, str):
        try:
            value.encode("utf-8")
        except UnicodeEncodeError:
            raise Invalid(f"{field}: contains a lone UTF-16 surrogate; text must be valid Unicode") from None
    elif isinstance(value, dict):
        for key, item in value.items():
            path = f"{field}.{str(key).encode('utf-8', 'replace').decode()}"  # printable even if the key is not
            check_document_text(path, key, depth + 1)
            check_document_text(path, item, depth + 1)
    elif isinstance(value, list):
        for i, item in enumerate(value):
            check_document_text(f"{field}[{i}]", item, depth + 1)


def check_name(name: Any) -> str:
    if not isinstance(name, str):
        raise Invalid(f"name: expected a string, got {_json_type(name)}")
    if not name.strip():
        raise Invalid("name: must not be empty")
    if len(name) > MAX_NAME:
        raise Invalid(f"name: {len(name)} characters, at most {MAX_NAME} allowed")
    return check_unicode("name", name)


def check_description(description: Any) -> str:
    if not isinstance(description, str):
        raise Invalid(f"description: expected a string, got {_json_type(description)}")
    if len(description) > MAX_DESCRIPTION:
        raise Invalid(f"description: {len(description)} characters, at most {MAX_DESCRIPTION} allowed")
    return check_unicode("description", description)


def check_tags(tags: Any) -> list[str]:
    if not isinstance(tags, list):
        raise Invalid(f"tags: expected a list of strings, got {_json_type(tags)}")
    if len(tags) > MAX_TAGS:
        raise Invalid(f"tags: {len(tags)} tags, at most {MAX_TAGS} allowed")
    out: list[str] = []
    for i, tag in enumerate(tags):
        if not isinstance(tag, str) or not TAG_RE.match(tag.strip().lower()):
            raise Invalid(f"tags[{i}]: {tag!r} is not a tag: 1-32 of a-z, 0-9, '-', '_', starting with a "
                          "letter or digit")
        if tag.strip().lower() not in out:
            out.append(tag.strip().lower())
    return out


def check_id(level_id: Any) -> str:
    if not isinstance(level_id, str) or not ID_RE.fullmatch(level_id):
        raise NotFound(f"no level with id {str(level_id)[:40]!r}")
    return level_id


def _encode_cursor(key: int, level_id: str) -> str:
    return base64.urlsafe_b64encode(json.dumps([key, level_id]).encode()).decode().rstrip("=")


def _decode_cursor(cursor: str) -> tuple[int, str]:
    try:
        key, level_id = json.loads(base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)))
        if (isinstance(key, int) and not isinstance(key, bool) and isinstance(level_id, str)
                and ID_RE.fullmatch(level_id) and abs(key) < 2**62):
            return key, level_id
    except (ValueError, TypeError, UnicodeDecodeError):
        pass
    raise StoreError("cursor: not a cursor from a previous page's \"next\"")


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
        """Set this token's vote on a level (+1, -1, or 0 to withdraw); one vote per token per level.

        With no token, a new one is issued and returned as "author_token". Returns the level's vote counts.
        """
        check_id(level_id)
        if value not in (-1, 0, 1) or isinstance(value, bool):
            raise Invalid("value: expected 1 (up), -1 (down) or 0 (withdraw)")
        with self._write() as conn:
            new_token = None
            if token is None:
                author, new_token = self.new_author(conn)
            else:
                author = self._author(conn, token)
            if conn.execute(select(levels_t.c.id).where(levels_t.c.id == level_id)).first() is None:
                raise NotFound(f"no level with id {level_id!r}")
            if value == 0:
                conn.execute(votes_t.delete().where(and_(votes_t.c.level_id == level_id,
                                                         votes_t.c.author_id == author)))
            else:
                # One statement that is atomic on both databases: no read-then-write race between voters.
                conn.execute(text(
                    "INSERT INTO votes (level_id, author_id, value, created) VALUES (:l, :a, :v, :t) "
                    "ON CONFLICT (level_id, author_id) DO UPDATE SET value = excluded.value"),
                    {"l": level_id, "a": author, "v": value, "t": now_ms()})
            up, down = self._vote_counts(conn, level_id)
        out = {"up": up, "down": down, "score": up - down, "value": value}
        if new_token:
            out["author_token"] = new_token
        return out

    def _vote_counts(self, conn: Connection, level_id: str) -> tuple[int, int]:
        row = conn.execute(select(func.count().filter(votes_t.c.value > 0), func.count().filter(votes_t.c.value < 0))
                           .where(votes_t.c.level_id == level_id)).one()
        return int(row[0]), int(row[1])

    def record_play(self, level_id: str, kind: str, *, solved: bool, steps: int, seconds: float,
                    recording: bytes | None = None, recording_path: str | None = None) -> int:
        """Record one finished play; returns its id.

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
            try:
                result = conn.execute(plays_t.insert().values(
                    level_id=level_id, kind=kind, solved=solved, steps=steps, seconds=float(seconds),
                    created=now_ms(), recording=recording, recording_path=recording_path).returning(plays_t.c.id))
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
    @staticmethod
    def _stats_subqueries(level_id: str | None = None):
        human = plays_t.c.kind == "human"
        agent = plays_t.c.kind == "agent"
        record = and_(human, plays_t.c.solved, plays_t.c.recording_path.is_not(None))
        plays = (select(
            plays_t.c.level_id,
            func.count().label("plays"),
            func.count().filter(human).label("human_plays"),
            func.count().filter(and_(human, plays_t.c.solved)).label("human_solved"),
            func.count().filter(agent).label("agent_plays"),
            func.count().filter(and_(agent, plays_t.c.solved)).label("agent_solved"),
            # Best times come only from records: human solves whose recording server.gallery.runs verified by
            # replay and kept (recording_path set; it keeps the best one's only, the best time's play).
            func.min(case((record, plays_t.c.seconds))).label("best_human_seconds"),
            func.min(case((record, plays_t.c.steps))).label("best_human_steps"),
            func.count().filter(record).label("best_runs"),
        ).where(plays_t.c.level_id == level_id if level_id else True).group_by(plays_t.c.level_id).subquery("p"))
        votes = (select(
            votes_t.c.level_id,
            func.count().filter(votes_t.c.value > 0).label("up"),
            func.count().filter(votes_t.c.value < 0).label("down"),
        ).where(votes_t.c.level_id == level_id if level_id else True).group_by(votes_t.c.level_id).subquery("v"))
        return plays, votes

    def _select(self, level_id: str | None = None):
        # For one level the aggregates are filtered inside the subqueries: SQLite does not push the outer
        # WHERE into a GROUP BY subquery, and would otherwise aggregate every play in the gallery.
        p, v = self._stats_subqueries(level_id)
        n = lambda col: func.coalesce(col, 0)
        human_plays, human_solved = n(p.c.human_plays), n(p.c.human_solved)
        keys = {
            "newest": levels_t.c.created,
            "top": n(v.c.up) - n(v.c.down),
            "played": n(p.c.plays),
            # Parts per million of human plays solved (an integer, so cursors compare exactly); unplayed last.
            "hardest": case((human_plays == 0, 1_000_001), else_=human_solved * 1_000_000 / human_plays),
        }
        columns = [levels_t.c.id, levels_t.c.name, levels_t.c.description, levels_t.c.author_id,
                   levels_t.c.created, levels_t.c.updated, levels_t.c.parent_id, levels_t.c.size,
                   n(p.c.plays).label("plays"), human_plays.label("human_plays"), human_solved.label("human_solved"),
                   n(p.c.agent_plays).label("agent_plays"), n(p.c.agent_solved).label("agent_solved"),
                   p.c.best_human_seconds, p.c.best_human_steps, n(v.c.up).label("up"), n(v.c.down).label("down"),
                   n(p.c.best_runs).label("best_runs")]
        base = (select(*columns).select_from(levels_t.outerjoin(p, p.c.level_id == levels_t.c.id)
                                             .outerjoin(v, v.c.level_id == levels_t.c.id)))
        return base, keys

    def _tags(self, conn: Connection, ids: list[str]) -> dict[str, list[str]]:
        out: dict[str, list[str]] = {i: [] for i in ids}
        if ids:
            for row in conn.execute(select(tags_t.c.level_id, tags_t.c.tag).where(tags_t.c.level_id.in_(ids))
                                    .order_by(tags_t.c.tag)):
                out[row.level_id].append(row.tag)
        return out

    @staticmethod
    def _summary(row, tags: list[str]) -> dict:
        rate = lambda solved, plays: (solved / plays) if plays else None
        return {
            "id": row.id, "name": row.name, "description": row.description,
            "author": row.author_id, "created": row.created, "updated": row.updated, "parent": row.parent_id,
            "size": row.size, "tags": tags,
            "stats": {
                "plays": int(row.plays), "human_plays": int(row.human_plays), "human_solved": int(row.human_solved),
                "human_solve_rate": rate(row.human_solved, row.human_plays),
                "agent_plays": int(row.agent_plays), "agent_solved": int(row.agent_solved),
                "agent_solve_rate": rate(row.agent_solved, row.agent_plays),
                "best_human_seconds": row.best_human_seconds,
                "best_human_steps": None if row.best_human_steps is None else int(row.best_human_steps),
                "has_best_run": int(row.best_runs) > 0,
                "votes_up": int(row.up), "votes_down": int(row.down), "score": int(row.up) - int(row.down),
            },
        }

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
        query, keys = self._select()
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
            last_key, last_id = _decode_cursor(cursor)
            if ascending:
                query = query.where(or_(key > last_key, and_(key == last_key, levels_t.c.id > last_id)))
            else:
                query = query.where(or_(key < last_key, and_(key == last_key, levels_t.c.id < last_id)))
        order = (key.asc(), levels_t.c.id.asc()) if ascending else (key.desc(), levels_t.c.id.desc())
        with self._read() as conn:
            rows = conn.execute(query.order_by(*order).limit(limit + 1)).all()
            page = rows[:limit]
            tags = self._tags(conn, [r.id for r in page])
        items = [self._summary(r, tags[r.id]) for r in page]
        nxt = _encode_cursor(int(page[-1].sort_key), page[-1].id) if len(rows) > limit else None
        return items, nxt

    def get_level(self, level_id: str) -> dict:
        """Metadata, stats and the level document (our format) of one level."""
        check_id(level_id)
        query, _ = self._select(level_id)
        with self._read() as conn:
            row = conn.execute(query.add_columns(levels_t.c.level_json).where(levels_t.c.id == level_id)).first()
            if row is None:
                raise NotFound(f"no level with id {level_id!r}")
            out = self._summary(row, self._tags(conn, [level_id])[level_id])
        out["level"] = json.loads(row.level_json)
        return out

    def stats(self, level_id: str) -> dict:
        check_id(level_id)
        query, _ = self._select(level_id)
        with self._read() as conn:
            row = conn.execute(query.where(levels_t.c.id == level_id)).first()
        if row is None:
            raise NotFound(f"no level with id {level_id!r}")
        return self._summary(row, [])["stats"]

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


def check_admin(token: str | None, admin_token: str | None) -> bool:
    return bool(token and admin_token and hmac.compare_digest(token.encode(), admin_token.encode()))
