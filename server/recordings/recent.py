"""Each tab's last play in the gallery's database (table `recent_recordings`), so a reload finds it again.

    table = RecentTable(store, max_files=32, max_bytes=64 << 20)   # store: the gallery's server.gallery.store.Store
    table.put(tab, StoredPlay(...))      # the tab's finished recording: replaces an older play of the tab
    table.get(tab)                       # the tab's last play, or None
    table.touch(tabs); table.sweep()     # the open tabs' rows stay; closed tabs' go after keep_s or over the caps

A tab is named by its tab key: a random id static/keys.js keeps in the tab's sessionStorage and sends with every
/keys hello (Session.tab_key). sessionStorage is per tab and survives a reload and a reconnect, whichever process the
proxy sends the tab to. The draft id is not in the address while the tab shows a gallery level (`?level=`), so
every reload of such a tab got a new one; the author token is per browser (every tab and the gallery page share it)
and a tab that never saved or played a gallery level has none.

The PlayRecorder (server.recordings.recorder) writes a play to its own folder first, and puts it here only once the
file is complete (after the Recorder's close: footer, fsync, rename), in one statement, so a row is always a whole
recording; a failed put is logged and changes nothing. A late put of an older play (the play a reload cut short,
finished on the old process after the tab played again on the new one) never replaces a newer one (`ended`).

Retention, across processes: one row per tab (the primary key), so each tab keeps only its last play. A process
marks the rows of its open tabs as seen every HEARTBEAT_S (and at a tab's close); a row not seen for keep_s (the
tab closed, or its process died) is removed, and over max_files rows or max_bytes bytes the oldest-seen go first,
except rows seen within LIVE_S (an open tab's: its last play is never removed, as in the folder). Only finished
recordings are rows: a process's play in progress is a partial file in its own folder, which no sweep here touches.

Why the database and not files or an object store: a recording is 20-100 KB (a ten-minute play a few MB) and there
is one per tab, as for best runs (server.gallery.runs); one row per tab makes a replacement atomic and the caps one
query, and there is no second service to run. With SQLite (one process) the same table sits in the gallery file.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Iterable

from sqlalchemy import select, text, update

from server.gallery.schema import recent_recordings_t

log = logging.getLogger(__name__)

HEARTBEAT_S = 60.0  # how often a process marks its open tabs' rows as seen (one UPDATE)
LIVE_S = 3 * HEARTBEAT_S  # a row seen this recently is an open tab's (two heartbeats may be late)
# With several processes on one PostgreSQL database the table holds every process's tabs: room for a hundred
# players at once, five recordings each (20-100 KB each, so usually far below the bytes cap).
SHARED_RECENT_MAX_FILES = 500
SHARED_RECENT_MAX_BYTES = 256 << 20

_UPSERT = text(
    "INSERT INTO recent_recordings (tab, name, player, level_id, result, steps, seconds, ended, seen, size_bytes, "
    "data) VALUES (:tab, :name, :player, :level_id, :result, :steps, :seconds, :ended, :seen, :size_bytes, :data) "
    "ON CONFLICT (tab) DO UPDATE SET name = excluded.name, player = excluded.player, level_id = excluded.level_id, "
    "result = excluded.result, steps = excluded.steps, seconds = excluded.seconds, ended = excluded.ended, "
    "seen = excluded.seen, size_bytes = excluded.size_bytes, data = excluded.data "
    "WHERE recent_recordings.ended <= excluded.ended")
# Deleted only if not seen since the sweep looked (a play stored or a tab marked meanwhile keeps its row).
_DELETE_UNSEEN = text("DELETE FROM recent_recordings WHERE tab = :tab AND seen = :seen")


@dataclasses.dataclass
class StoredPlay:
    """A tab's finished recording and what the Recordings folder says about it."""

    name: str  # the file name it had (play-<time>-<random>.mcap)
    player: str
    level_id: str | None
    result: str  # solved | failed | truncated | nan | stopped
    steps: int
    seconds: float
    ended: int  # when the play ended, ms since the epoch: the newest play of a tab wins
    data: bytes


class RecentTable:
    """The `recent_recordings` rows of one gallery Store; the caps and keep time apply to the whole table."""

    def __init__(self, store, *, max_files: int, max_bytes: int, keep_s: float, live_s: float = LIVE_S,
                 heartbeat_s: float = HEARTBEAT_S):
        if max_files < 1 or max_bytes < 1:
            raise ValueError(f"recent recordings need room for one: max_files={max_files}, max_bytes={max_bytes}")
        self.store = store
        self.max_files, self.max_bytes = max_files, max_bytes
        self.keep_s, self.live_s, self.heartbeat_s = keep_s, live_s, heartbeat_s

    def put(self, tab: str, play: StoredPlay, now: float | None = None) -> bool:
        """Keep `play` as the tab's last play; False (logged) when it is larger than the bytes cap, or when the
        row holds a later play of the tab already."""
        if len(play.data) > self.max_bytes:
            log.info("recording %s (%d bytes) is larger than the recent recordings' cap (%d bytes): not shared",
                     play.name, len(play.data), self.max_bytes)
            return False
        stamp = _ms(now)
        values = dataclasses.asdict(play)
        values.update(tab=tab, player=play.player[:100], seen=stamp, size_bytes=len(play.data))
        with self.store._write() as conn:
            return conn.execute(_UPSERT, values).rowcount > 0

    def get(self, tab: str) -> StoredPlay | None:
        t = recent_recordings_t.c
        with self.store._read() as conn:
            row = conn.execute(select(t.name, t.player, t.level_id, t.result, t.steps, t.seconds, t.ended, t.data)
                               .where(t.tab == tab)).first()
        if row is None:
            return None
        return StoredPlay(row.name, row.player, row.level_id, row.result, int(row.steps), float(row.seconds),
                          int(row.ended), bytes(row.data))

    def touch(self, tabs: Iterable[str], now: float | None = None) -> None:
        """Mark these tabs' rows as seen now (open tabs, or a tab closing: its keep time starts)."""
        tabs = sorted(set(tabs))
        if tabs:
            with self.store._write() as conn:
                conn.execute(update(recent_recordings_t).where(recent_recordings_t.c.tab.in_(tabs))
                             .values(seen=_ms(now)))

    def sweep(self, now: float | None = None) -> list[str]:
        """Remove the rows not seen for keep_s, then, oldest seen first, those that put the table over max_files or
        max_bytes, sparing rows seen within live_s (open tabs). Returns the removed tabs."""
        removed = []
        with self.store._write() as conn:
            for tab, seen in self._doomed(conn, _ms(now)):  # a few rows at a time: those over the limits
                if conn.execute(_DELETE_UNSEEN, {"tab": tab, "seen": seen}).rowcount:
                    removed.append(tab)
        return removed

    def _doomed(self, conn, stamp: int) -> list[tuple[str, int]]:
        """(tab, seen) of the rows to remove, oldest seen first."""
        t = recent_recordings_t.c
        rows = conn.execute(select(t.tab, t.seen, t.size_bytes).order_by(t.seen, t.tab)).all()
        count, total = len(rows), sum(row.size_bytes for row in rows)
        doomed = []
        for row in rows:
            over = count > self.max_files or total > self.max_bytes
            age = stamp - row.seen
            if age < self.live_s * 1000 or not (over or age > self.keep_s * 1000):
                continue
            doomed.append((row.tab, row.seen))
            count, total = count - 1, total - row.size_bytes
        return doomed


def _ms(now: float | None) -> int:
    return int((time.time() if now is None else now) * 1000)
