"""Drafts in the gallery's database (table `drafts`), shared by every server process on it.

    drafts = TableDraftStore(store)          # store: the gallery's server.gallery.store.Store
    drafts.save_later(draft_id, document)    # same interface as DraftStore (server.drafts.store)

With several `kinetix serve` processes behind one address (docs/deploy.md) a tab may reload through another
process, or come back there after its process died: the draft, undo and redo included, must be where every
process finds it. The document is the same JSON as a draft file, stored as bytes (a bytea on PostgreSQL): a draft
with a full undo history is ~0.5 MB and at most MAX_DRAFT_BYTES, far inside what a row holds (PostgreSQL moves
and compresses large values out of line by itself), and one row per draft keeps a write atomic without files.
The same age limit and cap as the files apply (`clean_up`).
"""

from __future__ import annotations

import time

from sqlalchemy import delete, select, update
from sqlalchemy.exc import IntegrityError

from server.drafts.store import DRAFT_MAX_AGE_S, MAX_DRAFT_BYTES, DraftError, DraftStore
from server.gallery.schema import drafts_t, now_ms

# Drafts kept at most in the shared table: several processes serve many more tabs than one (DRAFT_CAP, 200, is
# one process's); ~0.5 MB for a draft with a full undo history, so at most ~1 GB, usually a tenth of that.
SHARED_DRAFT_CAP = 2000


class TableDraftStore(DraftStore):
    """DraftStore whose documents live in the gallery database's `drafts` table."""

    def __init__(self, store, *, max_age_s: float = DRAFT_MAX_AGE_S, cap: int = SHARED_DRAFT_CAP):
        self.store = store  # the gallery Store: its engine, and its write transactions (BEGIN IMMEDIATE on SQLite)
        super().__init__(None, max_age_s=max_age_s, cap=cap)

    def _write_bytes(self, draft_id: str, data: bytes) -> None:
        self.path(draft_id)
        if len(data) > MAX_DRAFT_BYTES:
            raise DraftError(f"draft {draft_id} is {len(data)} bytes, more than a draft can be")
        stamp = now_ms()
        with self.store._write() as conn:
            if conn.execute(update(drafts_t).where(drafts_t.c.id == draft_id)
                            .values(document=data, updated=stamp)).rowcount:
                return
        try:
            with self.store._write() as conn:
                conn.execute(drafts_t.insert().values(id=draft_id, document=data, updated=stamp))
        except IntegrityError:  # another process inserted it meanwhile: the newest write wins, as with files
            with self.store._write() as conn:
                conn.execute(update(drafts_t).where(drafts_t.c.id == draft_id).values(document=data, updated=stamp))

    def _read_bytes(self, draft_id: str) -> bytes | None:
        with self.store._read() as conn:
            row = conn.execute(select(drafts_t.c.document).where(drafts_t.c.id == draft_id)).first()
        return None if row is None else bytes(row.document)

    def _touch(self, draft_id: str) -> None:
        with self.store._write() as conn:
            conn.execute(update(drafts_t).where(drafts_t.c.id == draft_id).values(updated=now_ms()))

    def _remove(self, draft_id: str) -> None:
        with self.store._write() as conn:
            conn.execute(delete(drafts_t).where(drafts_t.c.id == draft_id))

    def clean_up(self, now: float | None = None) -> list[str]:
        """Remove drafts unused for max_age_s and the oldest beyond `cap`; returns their ids."""
        now = time.time() if now is None else now
        with self.store._write() as conn:
            rows = conn.execute(select(drafts_t.c.id, drafts_t.c.updated).order_by(drafts_t.c.updated)).all()
            old = [r.id for r in rows if now * 1000 - r.updated > self.max_age_s * 1000]
            gone = set(old)
            left = [r.id for r in rows if r.id not in gone]
            old += left[:max(0, len(left) - self.cap)]
            if old:
                conn.execute(delete(drafts_t).where(drafts_t.c.id.in_(old)))
        return old
