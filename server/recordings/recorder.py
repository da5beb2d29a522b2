"""Every browser play, human or agent, recorded to an MCAP file (kinetix.recording.Recorder), without slowing play.

`PlayRecorder` is a session.PlayListener (`manager.add_listener(PlayRecorder(directory))`):
- play_started sets up a recording under `<directory>/recent/` with who plays, the gallery level id (if any),
  the seed (0: a level's start is fixed) and the env config and params the play steps with; the Recorder itself
  is opened on the finisher thread (LiveRecording.open_file), so starting a play costs 0.1 ms;
- play_stepped hands the action, reward, flags and the bodies' state after the step to the Recorder's queue
  (microseconds: the Recorder encodes and writes on its own thread) and keeps the state numbers (and the kept
  frames) in memory for a download of a play still running;
- frame_pushed passes every pushed JPEG on; the Recorder keeps at most one per 0.1 s of simulated time;
- play_ended (also for a play cut short by Stop, a new play or the tab going away) finishes the file on the
  finisher thread (close: drain, footer, fsync, rename), so the target is a complete recording or nothing. A play
  that ended before its first step (e.g. `?mode=play` waiting for a key when the tab reloads) is thrown away: it
  does not replace the tab's last play.

Times in the file are simulated seconds (steps x frame skip x dt), as for the gallery's best times, so a pause
or a slow machine does not stretch a recording.

Retention: `recent/` holds each tab's last play only (the previous one is deleted when the next one is
finished); after a tab closes its last file is kept for RECENT_KEEP_S and then swept (at start-up and whenever a
play finishes). On top of that `recent/` is capped at `max_files` files and `max_bytes` bytes (oldest removed
first; the last play of a tab still open is never removed, and there are at most max_sessions of those), so disk
use stays bounded however many tabs come and go. Partial files (`.part`) that no live process owns are removed at
start-up and on each sweep (kinetix.recording.remove_partial_files: the writing process holds a lock on them).
The gallery keeps best runs elsewhere (server.gallery.runs).

With the gallery's database (`table`, server.recordings.recent.RecentTable) a tab's last play also outlives its
session and this process: once its file is complete it is put in the table under the tab's key (Session.tab_key,
from the page's sessionStorage), and a new session of the same tab (a reload, or a reconnect through another
process) that has no play of its own yet gets it from there (`last_finished` fetches it into recent/). The table
has the same kinds of limits, across every process on the database: one row per tab, the open tabs' rows marked as
seen every HEARTBEAT_S by a thread here, closed tabs' rows removed after RECENT_KEEP_S or over its caps.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import logging
import math
import os
import re
import secrets
import tempfile
import threading
import time
import types
import weakref
from pathlib import Path

import numpy as np

from kinetix.recording import Recorder, RecordingError, remove_partial_files
from kinetix.recording.schema import MAX_FRAME_HZ
from server.play.hooks import PlayListener
from server.play.session import Session

log = logging.getLogger(__name__)

RECENT_DIR = "recent"
RECENT_KEEP_S = 3600.0  # how long the last play of a closed tab stays in recent/
RECENT_MAX_FILES = 32  # recent/ holds at most this many recordings (4 per tab of the default 8)...
RECENT_MAX_BYTES = 64 << 20  # ... and this many bytes (a typical play is 20-100 KB, a 10-minute one a few MB)
MAX_LOGGED_STEPS = 100_000  # the in-memory copy for downloads mid-play (episodes end at their time limit anyway)
MAX_LOGGED_FRAME_BYTES = 32 << 20  # its frames (flat drawings: 3-6 KB each, so about 10 minutes at 10 Hz)
FINISH_TIMEOUT_S = 60.0
STORED_NAME = re.compile(r"play-[A-Za-z0-9_-]{1,200}\.mcap")  # what play_started names a file (and a table row)


@dataclasses.dataclass
class Finished:
    """A finished recording of one play."""

    path: Path | None  # None when writing it failed (logged)
    player: str
    level_id: str | None
    result: str  # solved | failed | truncated | nan | stopped
    steps: int
    seconds: float


class _Fetched:
    """A tab's last play fetched from the table into recent/, held as a session's last play (like a LiveRecording's
    `done`)."""

    def __init__(self, finished: Finished):
        self.done: concurrent.futures.Future[Finished] = concurrent.futures.Future()
        self.done.set_result(finished)


class _Bodies(types.SimpleNamespace):
    """The bodies' dynamic state after a step as numpy arrays (what Recorder.add_step reads from a SimState)."""


class LiveRecording:
    """One play being recorded: its Recorder (opened on the finisher thread: building the level's JSON and npz
    takes milliseconds the thread starting the play should not spend) and an in-memory copy of its steps for
    downloads mid-play. Steps and frames that come before the Recorder is open wait in a list."""

    def __init__(self, path: Path, level_file, metadata: dict, env_config, env_params, tick: float):
        self.path = path
        self.level_file, self.metadata = level_file, metadata
        self.env_config, self.env_params = env_config, env_params
        self.tick = tick  # simulated seconds per agent step
        self.recorder: Recorder | None = None
        self.failed: BaseException | None = None  # the Recorder could not be opened (logged; nothing is written)
        self._pending: list[tuple] = []  # (method name, args, kwargs) until the Recorder is open
        self.lock = threading.Lock()
        self.steps: list[tuple] = []  # (t, action, reward, terminated, truncated, _Bodies, batch)
        self.count = 0  # steps recorded (the in-memory copy stops at MAX_LOGGED_STEPS, the file does not)
        self.frames: list[tuple[float, bytes]] = []  # kept frames (t, JPEG), up to MAX_LOGGED_FRAME_BYTES
        self._frame_bytes = 0
        self._last_frame_t = -math.inf
        self.open = True
        self.done: concurrent.futures.Future[Finished] = concurrent.futures.Future()

    def open_file(self) -> None:
        """Open the Recorder and hand it what arrived meanwhile (on the finisher thread, before any close)."""
        try:
            recorder = Recorder(self.path, self.level_file, metadata=self.metadata, env_config=self.env_config,
                                env_params=self.env_params)
        except (RecordingError, OSError) as error:  # e.g. a full disk: the play goes on unrecorded
            log.warning("play not recorded: %s", error)
            with self.lock:
                self.failed, self._pending = error, []
            return
        with self.lock:
            for name, args, kwargs in self._pending:
                getattr(recorder, name)(*args, **kwargs)
            self._pending = []
            self.recorder = recorder

    def _put(self, name: str, *args, **kwargs) -> None:  # with self.lock held
        if self.recorder is not None:
            getattr(self.recorder, name)(*args, **kwargs)
        elif self.failed is None:
            self._pending.append((name, args, kwargs))

    def add_step(self, action: np.ndarray, state, result) -> None:
        motion = getattr(result, "motion", None)  # play.Motion: fetched with the step's numbers
        if motion is None:
            # The step's arrays are computed already (the StepResult was fetched), so these copies do not wait.
            bodies = state.level.sim.bodies
            motion = (np.asarray(bodies.position), np.asarray(bodies.angle), np.asarray(bodies.velocity),
                      np.asarray(bodies.angular_velocity))
        position, angle, velocity, angular_velocity = motion
        snapshot = _Bodies(bodies=_Bodies(position=position, angle=angle, velocity=velocity,
                                          angular_velocity=angular_velocity))
        with self.lock:
            if not self.open:
                return
            self.count += 1
            t = self.count * self.tick
            batch = getattr(result, "batch", 1)
            item = (t, np.array(action), result.reward, result.terminated, result.truncated, snapshot, batch)
            if len(self.steps) < MAX_LOGGED_STEPS:
                self.steps.append(item)
            self._put("add_step", *item[1:6], t=t, batch=batch)

    def add_frame(self, jpeg: bytes) -> None:
        with self.lock:
            if not self.open or not self.count:
                return
            t = self.count * self.tick  # the frame shows the latest step
            if t >= self._last_frame_t + 1.0 / MAX_FRAME_HZ - 1e-6:  # the Recorder's own rule, checked before queueing
                self._last_frame_t = t
                self._put("add_frame", jpeg, t)
                if self._frame_bytes + len(jpeg) <= MAX_LOGGED_FRAME_BYTES:
                    self.frames.append((t, jpeg))
                    self._frame_bytes += len(jpeg)

    def stop_adding(self) -> None:
        with self.lock:
            self.open = False

    def snapshot(self) -> bytes:
        """The steps (and frames) so far as a complete recording of their own: written to a temporary file with a
        fresh Recorder and read back. For a download while the play still runs."""
        with self.lock:
            steps, frames = list(self.steps), list(self.frames)
        metadata = dict(self.metadata, partial=True)
        with tempfile.TemporaryDirectory(prefix="kinetix-snapshot-") as folder:
            path = Path(folder) / "snapshot.mcap"
            with Recorder(path, self.level_file, metadata=metadata, env_config=self.env_config,
                          env_params=self.env_params) as recorder:
                # In time order, as while playing: the file's log times never go backwards (the Recorder clamps
                # them), so frames must come between the steps they show, not after all of them.
                frames.reverse()
                for t, *item, batch in steps:
                    recorder.add_step(*item, t=t, batch=batch)
                    while frames and frames[-1][0] <= t:
                        recorder.add_frame(frames[-1][1], frames.pop()[0])
            return path.read_bytes()


class PlayRecorder(PlayListener):
    """Records every play of every session; see the module docstring. `enabled=False` records nothing."""

    def __init__(self, directory: str | os.PathLike, *, enabled: bool = True, max_files: int = RECENT_MAX_FILES,
                 max_bytes: int = RECENT_MAX_BYTES, table=None):
        self.directory = Path(directory)
        self.recent = self.directory / RECENT_DIR
        self.enabled = enabled
        self.max_files, self.max_bytes = max_files, max_bytes
        self.table = table if enabled else None  # server.recordings.recent.RecentTable, or None: this process only
        self._lock = threading.Lock()
        self._sessions: weakref.WeakSet[Session] = weakref.WeakSet()  # open sessions (their tabs' rows are seen)
        # Keyed by the session itself, weakly: an entry goes with its session, and a closed tab's last play stays
        # reachable for as long as someone holds the session (e.g. the gallery's record_play thread after a solve).
        self._live: weakref.WeakKeyDictionary[Session, LiveRecording] = weakref.WeakKeyDictionary()
        self._last: weakref.WeakKeyDictionary[Session, LiveRecording] = weakref.WeakKeyDictionary()
        # Closing a recording waits for its writer (drain, fsync): never on the play thread.
        self._finisher = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="kinetix-rec")
        self._stopping = threading.Event()
        self._heartbeat: threading.Thread | None = None
        if enabled:
            self.recent.mkdir(parents=True, exist_ok=True)
        if self.table is not None:
            self._heartbeat = threading.Thread(target=self._beat, name="kinetix-rec-seen", daemon=True)
            self._heartbeat.start()

    # ------------------------------------------------------------------ start-up and retention

    def clean_up(self) -> list[Path]:
        """Remove partial files that no live process owns (a killed server's; another live server's are kept) and
        sweep recent/ (see _sweep_recent). Returns what was removed."""
        removed = remove_partial_files(self.directory) + remove_partial_files(self.recent)
        self._sweep_table()
        return removed + self._sweep_recent()

    def _sweep_table(self) -> None:
        if self.table is None:
            return
        try:
            gone = self.table.sweep()
        except Exception:  # the database is away: the next sweep tries again; plays go on
            log.warning("sweeping the recent recordings' table failed", exc_info=True)
            return
        if gone:
            log.debug("removed %d recent recordings from the table", len(gone))

    def _beat(self) -> None:
        """Mark the open tabs' rows as seen (so no sweep in any process removes them) and sweep, every HEARTBEAT_S."""
        while not self._stopping.wait(self.table.heartbeat_s):
            with self._lock:
                tabs = {s.tab_key for s in self._sessions if getattr(s, "tab_key", None) and not s.closed}
            try:
                self.table.touch(tabs)
            except Exception:
                log.warning("marking open tabs' recent recordings failed", exc_info=True)
            self._sweep_table()

    def _sweep_recent(self) -> list[Path]:
        """Remove, oldest first, the recent/ files no open tab holds that are older than RECENT_KEEP_S or that put
        recent/ over max_files or max_bytes; and partial files no process owns."""
        removed = remove_partial_files(self.recent)
        with self._lock:
            keep = {r.path for r in self._live.values()}
            keep |= {r.done.result().path for r in self._last.values() if r.done.done()}
        files = []
        for path in self.recent.glob("*.mcap"):
            try:
                stat = path.stat()
            except FileNotFoundError:
                continue
            files.append((stat.st_mtime, path.name, path, stat.st_size))
        files.sort()  # oldest first (by name for equal times)
        count, total = len(files), sum(size for *_, size in files)
        now = time.time()
        for mtime, _, path, size in files:
            over = count > self.max_files or total > self.max_bytes
            if path in keep or not (over or now - mtime > RECENT_KEEP_S):
                continue
            try:
                path.unlink()
                removed.append(path)
            except FileNotFoundError:
                pass
            count, total = count - 1, total - size
        return removed

    # ------------------------------------------------------------------ PlayListener

    def session_opened(self, session: Session) -> None:
        with self._lock:
            self._sessions.add(session)

    def play_started(self, session: Session, level_file, params) -> None:
        if not self.enabled:
            return
        stepper = session._play[0]
        metadata = {"player": session.player, "name": getattr(session.editor.spec, "name", "") or "",
                    "level_id": session.gallery_id or "", "seed": 0, "source": "browser"}
        path = self.recent / f"play-{time.strftime('%Y%m%d-%H%M%S')}-{secrets.token_hex(4)}.mcap"
        live = LiveRecording(path, level_file, metadata, stepper.env.config, params,
                             float(params.sim.dt) * stepper.frame_skip)
        try:
            self._finisher.submit(live.open_file)  # the same one thread closes it later, so always after this
        except RuntimeError:  # shutting down
            return
        with self._lock:
            previous = self._live.pop(session, None)
            self._live[session] = live
        if previous is not None:  # not ended (cannot happen through Session, which ends a play before the next)
            self._finish(session, previous, "stopped", previous.count)

    def play_stepped(self, session: Session, action: np.ndarray, state, result) -> None:
        with self._lock:
            live = self._live.get(session)
        if live is not None:
            live.add_step(action, state, result)

    def frame_pushed(self, session: Session, jpeg: bytes, frame: np.ndarray) -> None:
        with self._lock:
            live = self._live.get(session)
        if live is not None:
            live.add_frame(jpeg)

    def play_ended(self, session: Session, result: str, steps: int, seconds: float) -> None:
        with self._lock:
            live = self._live.pop(session, None)
        if live is not None:
            self._finish(session, live, result, steps)

    def session_closed(self, session: Session) -> None:
        with self._lock:
            live = self._live.pop(session, None)
            self._sessions.discard(session)
        if live is not None:  # Session.close ends a running play first; this is a safety net
            self._finish(session, live, "stopped", live.count)
        tab = getattr(session, "tab_key", None)
        if self.table is not None and tab:
            try:  # after the store of its last play (same thread): the tab's keep time starts now
                self._finisher.submit(self._touch, tab)
            except RuntimeError:  # shutting down
                pass

    def _touch(self, tab: str) -> None:
        try:
            self.table.touch([tab])
        except Exception:
            log.warning("marking a closed tab's recent recording failed", exc_info=True)

    # ------------------------------------------------------------------ finishing

    def _finish(self, session: Session, live: LiveRecording, result: str, steps: int) -> None:
        live.stop_adding()
        if not live.count:  # ended before its first step (a play waiting for its first key that the tab left, or
            # Esc): nothing was played, so it replaces neither the tab's last play nor, after a reload, its row
            self._submit(self._drop, live, result)
            return
        with self._lock:
            previous = self._last.get(session)
            self._last[session] = live
        tab = getattr(session, "tab_key", None) if self.table is not None else None
        ended = time.time()  # the order of a tab's plays, even when two processes finish them
        self._submit(self._close, live, previous, result, steps, tab, ended)

    def _submit(self, function, *args) -> None:
        try:
            self._finisher.submit(function, *args)
        except RuntimeError:  # the server is shutting down (the finisher is closed): do it here
            function(*args)

    def _drop(self, live: LiveRecording, result: str) -> None:
        """Throw away the recording of a play that never stepped (its partial file goes)."""
        try:
            if live.recorder is not None:
                live.recorder.abort()
        except (RecordingError, OSError) as error:
            log.warning("recording %s not removed: %s", live.path.name, error)
        meta = live.metadata
        live.done.set_result(Finished(None, meta["player"], meta["level_id"] or None, result, 0, 0.0))

    def _close(self, live: LiveRecording, previous: LiveRecording | _Fetched | None, result: str, steps: int,
               tab: str | None = None, ended: float = 0.0) -> None:
        path = None
        live.steps, live.frames = [], []  # only a running play's download needs them; _last keeps this object
        try:
            if live.recorder is not None:  # None: it could not be opened (logged)
                path = live.recorder.close()
        except (RecordingError, OSError) as error:
            log.warning("recording %s not finished: %s", live.path.name, error)
        except Exception:  # a bug must not leave `done` unresolved (the gallery and downloads wait on it)
            log.exception("recording %s not finished", live.path.name)
        meta = live.metadata
        finished = Finished(path, meta["player"], meta["level_id"] or None, result, steps, steps * live.tick)
        if tab is not None and path is not None:  # before `done`: once the play is finished, it is shared
            self._share(tab, finished, ended)
        live.done.set_result(finished)
        if previous is not None and previous.done.done():
            old = previous.done.result().path
            if old is not None and old != path:
                old.unlink(missing_ok=True)  # recent/ keeps each tab's last play only
        try:
            self._sweep_recent()
        except OSError:
            log.debug("sweeping recent recordings failed", exc_info=True)
        if tab is not None:
            self._sweep_table()

    def _share(self, tab: str, finished: Finished, ended: float) -> None:
        """Put a complete recording in the table as the tab's last play; a failure is logged, the file stays."""
        from server.recordings.recent import StoredPlay  # with the gallery's database only (sqlalchemy)

        try:
            data = finished.path.read_bytes()
            self.table.put(tab, StoredPlay(finished.path.name, finished.player, finished.level_id, finished.result,
                                           finished.steps, finished.seconds, int(ended * 1000), data))
        except Exception:  # e.g. the database is away: the tab still has its play until it closes
            log.warning("recording %s not shared", finished.path.name, exc_info=True)

    def close(self) -> None:
        """Finish every recording still open (server shutdown)."""
        self._stopping.set()
        with self._lock:
            live = list(self._live.values())
            self._live.clear()
        for recording in live:
            recording.stop_adding()
            if recording.count:
                self._finisher.submit(self._close, recording, None, "stopped", recording.count)
            else:
                self._finisher.submit(self._drop, recording, "stopped")
        self._finisher.shutdown(wait=True)
        if self._heartbeat is not None:
            self._heartbeat.join(timeout=10)

    # ------------------------------------------------------------------ for the tab's panel and the gallery

    def last_finished(self, session: Session, timeout: float = FINISH_TIMEOUT_S) -> Finished | None:
        """The session's last ended play once its file is finished (waits for it), or None if it has none."""
        with self._lock:
            live = self._last.get(session)
        if live is None:
            return self._fetch(session, timeout)
        try:
            return live.done.result(timeout=timeout)
        except concurrent.futures.TimeoutError:
            return None

    def _fetch(self, session: Session, timeout: float) -> Finished | None:
        """The tab's last play from the table (a session with no play of its own yet: a reload, or a reconnect
        through another process), copied into recent/ and held as the session's last play; None if there is none."""
        tab = getattr(session, "tab_key", None)
        if self.table is None or not tab:
            return None
        try:
            stored = self.table.get(tab)
        except Exception:
            log.warning("could not look up the tab's recent recording", exc_info=True)
            return None
        if stored is None or not STORED_NAME.fullmatch(stored.name):
            return None
        path = self.recent / stored.name
        partial = self.recent / f".{stored.name}.{secrets.token_hex(4)}.fetch.part"
        try:
            partial.write_bytes(stored.data)
            os.replace(partial, path)
        except OSError as error:
            log.warning("recording %s not fetched: %s", stored.name, error)
            return None
        finally:
            partial.unlink(missing_ok=True)
        fetched = _Fetched(Finished(path, stored.player, stored.level_id, stored.result, stored.steps,
                                    stored.seconds))
        with self._lock:
            held = self._last.setdefault(session, fetched)  # a play of its own that ended meanwhile comes first
        try:
            return held.done.result(timeout=timeout)
        except concurrent.futures.TimeoutError:
            return None

    def download(self, session: Session) -> tuple[str, bytes] | None:
        """(file name, bytes) of the session's current play (the steps so far) or else its last play."""
        with self._lock:
            live = self._live.get(session)
        if live is not None and live.count:
            return f"kinetix-play-{live.count}-steps-so-far.mcap", live.snapshot()
        finished = self.last_finished(session)
        if finished is None:
            return None
        if finished.path is None:
            raise RecordingError("the last play could not be recorded (see the server log)")
        try:
            return f"kinetix-play-{finished.result}-{finished.steps}-steps.mcap", finished.path.read_bytes()
        except FileNotFoundError:  # swept meanwhile
            return None
