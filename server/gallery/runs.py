"""Best runs: the gallery keeps the recording of the best human solve of each level, and only that one.

Best = fewest simulated seconds, ties broken by fewest steps, then by the earlier play. The kept run is shown as
the level's best run only while it set the best time: when a faster human solve has no recording (a server
started with --no-record, a recording that failed), the best time has no run to show and `best_run_file` says so
(None), rather than offering a slower run beside a better time. Retention rule: a level
has at most one recording file in the gallery (`best-<level>-<random>.mcap` in `store.recordings_dir`), named by
the `recording_path` of its play row. A new solve's recording is copied in only if it beats the kept one; then
the superseded row's `recording_path` is cleared and its file deleted. Files no row names (a crash between the
copy and the insert, a deleted level) are removed by `remove_orphans` at start-up. Every other play's file lives
only in the server's recent/ folder (server.recorder), one per tab.
"""

from __future__ import annotations

import logging
import os
import secrets
import shutil
import threading
from pathlib import Path

from sqlalchemy import and_, func, select, update

from server.gallery.store import Store, check_id, plays_t

log = logging.getLogger(__name__)

PREFIX = "best-"


def _best_seconds(conn, level_id: str) -> float | None:
    """The level's best human time (recorded or not), as the gallery's stats show it."""
    return conn.execute(select(func.min(plays_t.c.seconds)).where(
        and_(plays_t.c.level_id == level_id, plays_t.c.kind == "human", plays_t.c.solved))).scalar()


def _best_rows(conn, level_id: str):
    return conn.execute(
        select(plays_t.c.id, plays_t.c.seconds, plays_t.c.steps, plays_t.c.recording_path)
        .where(and_(plays_t.c.level_id == level_id, plays_t.c.kind == "human", plays_t.c.solved,
                    plays_t.c.recording_path.is_not(None)))
        .order_by(plays_t.c.seconds, plays_t.c.steps, plays_t.c.id)).all()


class BestRuns:
    """The best-run files of one Store (it needs `store.recordings_dir`)."""

    def __init__(self, store: Store):
        if store.recordings_dir is None:
            raise ValueError("the gallery has no recordings directory")
        self.store = store
        self.directory = Path(store.recordings_dir)
        self.directory.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()  # one prune at a time in this process (the database orders the rest)

    def best_run_file(self, level_id: str) -> Path | None:
        """The recording of the play that set the level's best time, or None (no recorded human solve, its file is
        gone, or a faster solve was not recorded)."""
        check_id(level_id)
        with self.store._read() as conn:
            rows = _best_rows(conn, level_id)
            best = _best_seconds(conn, level_id)
        for row in rows:
            if best is not None and row.seconds > best + 1e-9:  # the best time's play has no recording
                return None
            path = self.directory / row.recording_path
            if path.is_file():
                return path
        return None

    def offer(self, level_id: str, source: Path, steps: int, seconds: float) -> str | None:
        """Copy a finished human solve's recording into the gallery if it beats the level's kept best run;
        returns the file name to store with the play (`record_play(recording_path=...)`), or None."""
        with self.store._read() as conn:
            rows = _best_rows(conn, level_id)
        if rows and (rows[0].seconds, rows[0].steps) <= (seconds, steps):
            return None
        name = f"{PREFIX}{level_id}-{secrets.token_hex(6)}.mcap"
        target = self.directory / name
        partial = self.directory / f".{name}.copy.part"  # hidden and swept like the Recorder's partial files
        try:
            shutil.copyfile(source, partial)
            os.replace(partial, target)
        except OSError as error:
            partial.unlink(missing_ok=True)
            log.warning("best run of %s not kept: %s", level_id, error)
            return None
        return name

    def discard(self, name: str) -> None:
        """Delete a copied file whose play could not be recorded (e.g. the level was deleted meanwhile)."""
        (self.directory / Path(name).name).unlink(missing_ok=True)

    def prune(self, level_id: str) -> list[Path]:
        """Keep only the best recorded human solve of the level: clear the others' recording_path and delete
        their files (after the commit, so a failed transaction deletes nothing). Returns the deleted files."""
        with self._lock:
            with self.store._write() as conn:
                rows = _best_rows(conn, level_id)
                superseded = rows[1:]
                if superseded:
                    conn.execute(update(plays_t).where(plays_t.c.id.in_([r.id for r in superseded]))
                                 .values(recording_path=None))
            removed = []
            for row in superseded:
                path = self.directory / row.recording_path
                if path.name.startswith(PREFIX):
                    path.unlink(missing_ok=True)
                    removed.append(path)
            return removed

    def remove_orphans(self) -> list[Path]:
        """Delete best-run files that no play names (start-up)."""
        with self.store._read() as conn:
            named = {row[0] for row in conn.execute(select(plays_t.c.recording_path)
                                                    .where(plays_t.c.recording_path.is_not(None)))}
        removed = []
        for path in self.directory.glob(f"{PREFIX}*.mcap"):
            if path.name not in named:
                path.unlink(missing_ok=True)
                removed.append(path)
        return removed

    def candidate(self, recorder, session, result: str, steps: int, seconds: float,
                  player: str = "human") -> str | None:
        """For a finished play of a gallery level: the best-run file name to record with it, if this play is a
        human solve whose recording (server.recorder.PlayRecorder) beats the kept best run; else None. `player`:
        the recording's player ("human", or "race" for the human's side of a race, which is the session's play).
        Waits for the recording to be finished, so call it off the play thread (on_play_end runs on its own)."""
        if result != "solved" or recorder is None:
            return None
        finished = recorder.last_finished(session)
        if (finished is None or finished.path is None or finished.player != player or finished.result != "solved"
                or finished.level_id != session.gallery_id or finished.steps != steps):
            return None
        return self.offer(session.gallery_id, finished.path, steps, seconds)
