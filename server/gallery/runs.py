"""Best runs: the gallery keeps the recording of the best human solve of each level, and only that one.

Best = fewest simulated seconds, ties broken by fewest steps, then by the earlier play. A play sets a record only
with a recording that proves it (server.gallery.proof: re-simulated bitwise, the gallery's level, the claimed
steps): the best time and the best run come from the same verified play, in one code path (`offer`). A solve
without such a recording (a server started with --no-record, a recording that failed, was tampered with or does
not verify) counts as a play but sets no best time; the reason is logged once. Retention rule: a level
has at most one recording file in the gallery (`best-<level>-<random>.mcap` in `store.recordings_dir`), named by
the `recording_path` of its play row. A new solve's recording is copied in only if it beats the kept one; then
the superseded row's `recording_path` is cleared and its file deleted. Files no row names (a crash between the
copy and the insert, a deleted level) are removed by `remove_orphans` at start-up. Every other play's file lives
only in the server's recent/ folder (server.recordings.recorder), one per tab.

Several processes on one PostgreSQL gallery (docs/deploy.md) share the best runs: a kept recording is also
stored in the table `recording_files` (its bytes, under the same name) in the transaction before its play row, and
`best_run_file` fetches it into this process's recordings directory when it is not there yet (a cache: the name
changes whenever the best run does, so a cached file is never stale). A best run is 20-100 KB (a ten-minute one a
few MB) and a level keeps one, so a bytea row is the simplest shared storage that stays consistent with the play
that names it; an object store would be a second service to run and back up for no gain at these sizes.
"""

from __future__ import annotations

import logging
import os
import secrets
import shutil
import threading
from pathlib import Path

from sqlalchemy import and_, delete, select, update

from server.gallery.checks import StoreError, check_id
from server.gallery.proof import why_not_a_record
from server.gallery.schema import now_ms, plays_t, recording_files_t
from server.gallery.store import Store

log = logging.getLogger(__name__)

PREFIX = "best-"
ORPHAN_AGE_S = 600  # a shared recording no play names is removed only when this old (another process may be
#                     between storing the file and inserting its play row)


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
        self.shared = store.dialect != "sqlite"  # several processes: the files live in recording_files too
        self._said_unrecorded = False

    def best_run_file(self, level_id: str) -> Path | None:
        """The recording of the play that set the level's best time, or None (no verified human solve yet, or its
        file is gone)."""
        check_id(level_id)
        with self.store._read() as conn:
            rows = _best_rows(conn, level_id)
        for row in rows:
            if row.seconds > rows[0].seconds + 1e-9:  # a slower run is not the best time's
                return None
            path = self.directory / row.recording_path
            if path.is_file() or (self.shared and self._fetch(row.recording_path, path)):
                return path
        return None

    def _fetch(self, name: str, path: Path) -> bool:
        """Copy a shared best run into this process's directory (temporary name, then rename); False if absent."""
        with self.store._read() as conn:
            row = conn.execute(select(recording_files_t.c.data).where(recording_files_t.c.name == name)).first()
        if row is None:
            return False
        partial = self.directory / f".{name}.{secrets.token_hex(4)}.fetch.part"
        try:
            partial.write_bytes(bytes(row.data))
            os.replace(partial, path)
        finally:
            partial.unlink(missing_ok=True)
        return True

    def offer(self, level_id: str, source: Path | None, steps: int, seconds: float,
              player: str = "human") -> str | None:
        """If a finished human solve beats the level's best time and its recording `source` proves it
        (server.gallery.proof), copy the recording into the gallery and return the file name to store with the
        play (`record_play(recording_path=...)`): that play then is the best time and the best run. Else None
        (the reason logged). Re-simulates, so call it off the play thread."""
        with self.store._read() as conn:
            rows = _best_rows(conn, level_id)
        if rows and (rows[0].seconds, rows[0].steps) <= (seconds, steps):
            return None
        try:
            document = self.store.get_level(level_id)["level"]
        except StoreError as error:  # e.g. deleted meanwhile
            log.warning("play on %s sets no best time: %s", level_id, error)
            return None
        name = f"{PREFIX}{level_id}-{secrets.token_hex(6)}.mcap"
        target = self.directory / name
        partial = self.directory / f".{name}.copy.part"  # hidden and swept like the Recorder's partial files
        try:
            if source is not None:  # the proof reads the copy: the kept bytes are the verified bytes
                shutil.copyfile(source, partial)
            reason = why_not_a_record(None if source is None else partial, level_id=level_id, player=player,
                                      steps=steps, seconds=seconds, level_document=document)
            if reason is not None:
                log.warning("play on %s (%d steps, %.3f s) sets no best time: %s", level_id, steps, seconds, reason)
                partial.unlink(missing_ok=True)
                return None
            if self.shared:
                with self.store._write() as conn:
                    conn.execute(recording_files_t.insert().values(name=name, data=partial.read_bytes(),
                                                                   created=now_ms()))
            os.replace(partial, target)
        except OSError as error:
            partial.unlink(missing_ok=True)
            log.warning("best run of %s not kept: %s", level_id, error)
            return None
        return name

    def discard(self, name: str) -> None:
        """Delete a copied file whose play could not be recorded (e.g. the level was deleted meanwhile)."""
        (self.directory / Path(name).name).unlink(missing_ok=True)
        if self.shared:
            with self.store._write() as conn:
                conn.execute(delete(recording_files_t).where(recording_files_t.c.name == Path(name).name))

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
                    if self.shared:
                        conn.execute(delete(recording_files_t).where(
                            recording_files_t.c.name.in_([r.recording_path for r in superseded])))
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
        if self.shared:
            with self.store._write() as conn:
                conn.execute(delete(recording_files_t).where(
                    recording_files_t.c.name.not_in(select(plays_t.c.recording_path)
                                                    .where(plays_t.c.recording_path.is_not(None))),
                    recording_files_t.c.created < now_ms() - ORPHAN_AGE_S * 1000))
        removed = []
        for path in self.directory.glob(f"{PREFIX}*.mcap"):
            if path.name not in named:
                path.unlink(missing_ok=True)
                removed.append(path)
        return removed

    def candidate(self, recorder, session, result: str, steps: int, seconds: float,
                  player: str = "human") -> str | None:
        """For a finished play of a gallery level: the best-run file name to record with it, if this play is a
        human solve that beats the kept best run and whose recording (server.recordings.recorder.PlayRecorder) proves it
        (`offer`); else None. `player`:
        the recording's player ("human", or "race" for the human's side of a race, which is the session's play).
        Waits for the recording to be finished, so call it off the play thread (on_play_end runs on its own)."""
        if result != "solved":
            return None
        if recorder is None:  # kinetix serve --no-record: said once, not once per solve
            if not self._said_unrecorded:
                self._said_unrecorded = True
                log.warning("plays are not recorded (--no-record), so no play sets a best time")
            return None
        finished = recorder.last_finished(session)
        path = finished.path if finished is not None else None
        if finished is not None and (finished.player != player or finished.result != "solved"
                                     or finished.level_id != session.gallery_id or finished.steps != steps):
            path = None  # the session's last recording is another play's
        return self.offer(session.gallery_id, path, steps, seconds, player)
