"""Drafts: a tab's unsaved level and its undo history, kept on the server so a reload or a restart loses nothing.

    store = DraftStore(data_dir / "drafts")
    draft_id = store.new_id()
    store.save_later(draft_id, document)      # written by the store's thread; the newest document per id wins
    document = store.load(draft_id)           # None when there is no such draft; DraftError when it is unreadable
    store.discard(draft_id)

`server.drafts.table.TableDraftStore` keeps the same documents in the gallery's database instead, so that several
server processes behind one address share them (`kinetix serve --db postgresql://...`, docs/deploy.md).

One JSON file per draft (`<id>.json`), written to a temporary file, flushed to disk and renamed over the old one, so
a draft on disk is always a whole document (a crash leaves the previous version or a `.tmp` that `clean_up` removes).
Drafts untouched for DRAFT_MAX_AGE_S are removed, and beyond DRAFT_CAP files the oldest go first.

The document (`draft_document` / `read_draft`): {"format": "kinetix-draft", "version": 1, "gallery_id": id | null,
"level": snapshot, "undo": [snapshot, ...], "redo": [...]}, a snapshot being {"size": SizeClass fields,
"spec": LevelSpec fields}: the editor's own `LevelSpec` dataclasses written field for field, so a reopened draft
is exactly the level and history the tab had (building the level again on load would cost ~14 ms per snapshot).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import re
import secrets
import threading
import time
from pathlib import Path

from kinetix.formats import BodySpec, JointSpec, LevelSpec, ThrusterSpec
from kinetix.level import LevelError, LevelParams, SizeClass

log = logging.getLogger(__name__)

DRAFT_MAX_AGE_S = 30 * 24 * 3600  # a draft nobody opened or edited for 30 days is removed
DRAFT_CAP = 200  # drafts kept at most (the oldest go first); a draft with a full undo history is ~0.5 MB
CLEAN_EVERY_S = 3600  # a long-running server looks for old drafts after a write at most this often
MAX_DRAFT_BYTES = 16 << 20  # a larger file is not one of ours
DRAFT_FORMAT, DRAFT_VERSION = "kinetix-draft", 1
DRAFT_ID = re.compile(r"[A-Za-z0-9_-]{8,64}")  # what new_id makes (and what may name a file)
TUPLE_FIELDS = {"position", "velocity", "anchor", "anchor_a", "anchor_b", "gravity", "limits"}


class DraftError(ValueError):
    """A draft that cannot be read back; the message says which draft and why (meant for the user)."""


def valid_id(draft_id: object) -> bool:
    return isinstance(draft_id, str) and DRAFT_ID.fullmatch(draft_id) is not None


# ---------------------------------------------------------------- the document

def snapshot_json(spec: LevelSpec, size: SizeClass) -> dict:
    """One level state (the current one or an undo step) as JSON-ready data."""
    return {"size": dataclasses.asdict(size), "spec": dataclasses.asdict(spec)}


def draft_document(level: dict, undo: list[dict], redo: list[dict], gallery_id: str | None) -> dict:
    return {"format": DRAFT_FORMAT, "version": DRAFT_VERSION, "gallery_id": gallery_id, "level": level,
            "undo": undo, "redo": redo}


@dataclasses.dataclass
class Draft:
    """A draft read back: the level, its size class, the undo and redo stacks as (spec, size) pairs, oldest first."""

    spec: LevelSpec
    size: SizeClass
    undo: list[tuple[LevelSpec, SizeClass]]
    redo: list[tuple[LevelSpec, SizeClass]]
    gallery_id: str | None


def read_draft(document: object) -> Draft:
    """The Draft in a parsed document; DraftError naming the first field that is wrong."""
    if not isinstance(document, dict) or document.get("format") != DRAFT_FORMAT:
        raise DraftError("not a kinetix draft (no \"format\": \"kinetix-draft\")")
    if document.get("version") != DRAFT_VERSION:
        raise DraftError(f"draft version {document.get('version')!r} is not supported (expected {DRAFT_VERSION})")
    gallery_id = document.get("gallery_id")
    if gallery_id is not None and not isinstance(gallery_id, str):
        raise DraftError("gallery_id: expected a string or null")
    spec, size = _snapshot(document.get("level"), "level")
    stacks = []
    for key in ("undo", "redo"):
        items = document.get(key, [])
        if not isinstance(items, list):
            raise DraftError(f"{key}: expected a list")
        stacks.append([_snapshot(item, f"{key}[{i}]") for i, item in enumerate(items)])
    return Draft(spec, size, stacks[0], stacks[1], gallery_id)


def _snapshot(data: object, where: str) -> tuple[LevelSpec, SizeClass]:
    if not isinstance(data, dict):
        raise DraftError(f"{where}: expected an object with size and spec")
    size = _make(SizeClass, data.get("size"), f"{where}.size")
    fields = _fields(LevelSpec, data.get("spec"), f"{where}.spec")
    try:
        fields["bodies"] = [_make(BodySpec, b, f"{where}.spec.bodies[{i}]") for i, b in enumerate(fields["bodies"])]
        fields["joints"] = [_make(JointSpec, j, f"{where}.spec.joints[{i}]") for i, j in enumerate(fields["joints"])]
        fields["thrusters"] = [_make(ThrusterSpec, t, f"{where}.spec.thrusters[{i}]")
                               for i, t in enumerate(fields["thrusters"])]
    except TypeError:
        raise DraftError(f"{where}.spec: bodies, joints and thrusters must be lists") from None
    fields["params"] = _make(LevelParams, fields.get("params", {}), f"{where}.spec.params")
    if fields.get("size") is not None:
        fields["size"] = _make(SizeClass, fields["size"], f"{where}.spec.size")
    return LevelSpec(**fields), size


def _fields(cls, data: object, where: str) -> dict:
    """The fields of dataclass `cls` in `data`, checked: known names only, required ones present, plain values."""
    if not isinstance(data, dict):
        raise DraftError(f"{where}: expected an object")
    known = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise DraftError(f"{where}: unknown field {unknown[0]!r}")
    missing = [name for name, f in known.items() if name not in data
               and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    if missing:
        raise DraftError(f"{where}: missing field {missing[0]!r}")
    out = {}
    for name, value in data.items():
        if name in TUPLE_FIELDS and value is not None:
            if not (isinstance(value, list | tuple) and len(value) == 2 and all(_number(v) for v in value)):
                raise DraftError(f"{where}.{name}: expected two numbers")
            value = tuple(value)
        out[name] = value
    return out


def _number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _make(cls, data: object, where: str):
    fields = _fields(cls, data, where)
    if cls is not LevelSpec:
        for name, value in fields.items():
            if isinstance(value, dict) or (isinstance(value, list) and name != "vertices"):
                raise DraftError(f"{where}.{name}: unexpected {type(value).__name__}")
    try:
        return cls(**fields)
    except (LevelError, TypeError, ValueError) as error:
        raise DraftError(f"{where}: {error}") from None


# ---------------------------------------------------------------- the store

class DraftStore:
    """Draft files in one directory, written by a background thread (the newest document per draft wins)."""

    def __init__(self, directory: Path | None, *, max_age_s: float = DRAFT_MAX_AGE_S, cap: int = DRAFT_CAP):
        self.directory = Path(directory) if directory is not None else None  # None: a subclass stores elsewhere
        if self.directory is not None:
            self.directory.mkdir(parents=True, exist_ok=True)
        self.max_age_s, self.cap = max_age_s, cap
        self._cond = threading.Condition()
        self._pending: dict[str, dict] = {}  # draft id -> the newest document not yet written
        self._writing: str | None = None
        self._closed = False
        self._cleaned = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="kinetix-drafts", daemon=True)
        self._thread.start()

    @staticmethod
    def new_id() -> str:
        return secrets.token_urlsafe(12)

    def path(self, draft_id: str) -> Path:
        """The draft's file; DraftError for a string that is not a draft id (checked before any storage is used)."""
        if not valid_id(draft_id):
            raise DraftError(f"{draft_id!r} is not a draft id")
        return Path(self.directory or ".") / f"{draft_id}.json"

    # ------------------------------------------------------------ writing

    def save(self, draft_id: str, document: dict) -> None:
        """Write now (atomically: a temporary file flushed to disk, then renamed over the draft)."""
        self._write_bytes(draft_id, json.dumps(document, separators=(",", ":"), allow_nan=False).encode())

    def _write_bytes(self, draft_id: str, data: bytes) -> None:
        path = self.path(draft_id)
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
        try:
            with open(tmp, "wb") as file:
                file.write(data)
                file.flush()
                os.fsync(file.fileno())
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)

    def save_later(self, draft_id: str, document: dict) -> None:
        """Queue a write; a newer document for the same draft replaces one still waiting."""
        self.path(draft_id)  # a bad id fails here, in the caller
        with self._cond:
            self._pending[draft_id] = document
            self._cond.notify_all()

    def flush(self, draft_id: str | None = None, timeout: float = 10.0) -> bool:
        """Wait until the queued writes (of `draft_id`, or all) are on disk; False on timeout."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while (draft_id in self._pending or self._writing == draft_id) if draft_id else \
                    (self._pending or self._writing):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._pending and not self._closed:
                    self._cond.wait()
                if not self._pending:
                    return
                draft_id = next(iter(self._pending))
                document = self._pending.pop(draft_id)
                self._writing = draft_id
            try:
                self.save(draft_id, document)
            except Exception:  # a full disk must not stop the other drafts; the tab's next edit tries again
                log.exception("could not write draft %s", draft_id)
            finally:
                with self._cond:
                    self._writing = None
                    self._cond.notify_all()
            if time.monotonic() - self._cleaned > CLEAN_EVERY_S:
                self._cleaned = time.monotonic()
                try:
                    self.clean_up()
                except Exception:  # a full disk or a lost database connection must not stop the writes
                    log.exception("could not remove old drafts")

    def close(self) -> None:
        """Write what is queued, then stop the thread."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self._thread.join(timeout=30)

    # ------------------------------------------------------------ reading and removing

    def load(self, draft_id: str) -> Draft | None:
        """The draft (after any queued write of it), None if there is none; DraftError if it cannot be read."""
        self.path(draft_id)  # a bad id fails here
        self.flush(draft_id)
        data = self._read_bytes(draft_id)
        if data is None:
            return None
        try:
            document = json.loads(data)
        except (UnicodeDecodeError, json.JSONDecodeError) as error:
            raise DraftError(f"draft {draft_id} is not valid JSON ({error})") from None
        except RecursionError:
            raise DraftError(f"draft {draft_id} is nested too deeply") from None
        try:
            draft = read_draft(document)
        except DraftError as error:
            raise DraftError(f"draft {draft_id}: {error}") from None
        self._touch(draft_id)  # opened counts as used: the age limit counts from the last use
        return draft

    def _read_bytes(self, draft_id: str) -> bytes | None:
        path = self.path(draft_id)
        try:
            size = path.stat().st_size
            if size > MAX_DRAFT_BYTES:
                raise DraftError(f"draft {draft_id} is {size} bytes, more than a draft can be")
            return path.read_bytes()
        except FileNotFoundError:
            return None
        except OSError as error:
            raise DraftError(f"draft {draft_id} cannot be read: {error.strerror}") from None

    def _touch(self, draft_id: str) -> None:
        os.utime(self.path(draft_id))

    def _remove(self, draft_id: str) -> None:
        self.path(draft_id).unlink(missing_ok=True)

    def discard(self, draft_id: str) -> None:
        self.path(draft_id)
        with self._cond:
            self._pending.pop(draft_id, None)
        self.flush(draft_id)
        self._remove(draft_id)

    def clean_up(self, now: float | None = None) -> list:
        """Remove drafts older than max_age_s, the oldest beyond `cap`, and temporary files of a crash."""
        now = time.time() if now is None else now
        removed, drafts = [], []
        for path in self.directory.iterdir():
            try:
                mtime = path.stat().st_mtime
            except FileNotFoundError:
                continue
            stale_tmp = path.name.endswith(".tmp") and now - mtime > 60
            if stale_tmp or (path.suffix == ".json" and now - mtime > self.max_age_s):
                path.unlink(missing_ok=True)
                removed.append(path)
            elif path.suffix == ".json":
                drafts.append((mtime, path))
        drafts.sort()
        for _, path in drafts[:max(0, len(drafts) - self.cap)]:
            path.unlink(missing_ok=True)
            removed.append(path)
        return removed
