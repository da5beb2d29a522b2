"""The SessionManager: every tab's Session, created on viser's connect and closed on disconnect, capped at
--max-sessions; the one play thread (server.play.scheduler), the frame encoders and the listeners they share."""

from __future__ import annotations

import concurrent.futures
import logging
import threading
from collections.abc import Callable

from server.play import draw
from server.play.frames import preview_jpeg
from server.play.hooks import PlayListener
from server.play.scheduler import PlayScheduler
from server.play.session import Session
from server.play.warmup import PREPARING

log = logging.getLogger(__name__)


class SessionManager:
    """All sessions of one server: created on viser connect, removed on disconnect, capped at `max_sessions`."""

    def __init__(self, server, *, max_sessions: int = 8, initial_level: Callable | None = None,
                 editor_factory: Callable | None = None, warmup=None,
                 page_query: Callable[[object], str | None] | None = None):
        self.server = server
        # The server's background compiles (server.play.warmup.WarmUp), or None: every play step compiles on use.
        self.warmup = warmup
        if warmup is not None:
            warmup.on_progress(self._warmup_progressed)
        self.editor_factory = editor_factory  # (level, size=) -> Editor; default server.editor.Editor
        # (session, "?level=...&mode=play") -> None: set by the gallery integration to open a level from the URL.
        self.on_query: Callable[[Session, str], None] | None = None
        self.on_session_gui: Callable[[Session], None] | None = None  # adds GUI to a new session (the gallery's)
        # (session, "solved" | "failed" | "truncated" | "nan", steps, seconds) after every finished play.
        self.on_play_end: Callable[[Session, str, int, float], None] | None = None
        self.listeners: list[PlayListener] = []  # see PlayListener; add with add_listener
        self.scheduler = PlayScheduler()  # the one thread that steps and draws every playing session
        # Play frames are JPEG-encoded and sent here, in parallel with the play thread drawing the next one.
        self.encoder = concurrent.futures.ThreadPoolExecutor(max_workers=2, thread_name_prefix="kinetix-frames")
        self.max_sessions = max_sessions
        self.initial_level = initial_level  # (client) -> LevelFile | None (kinetix serve --level)
        # (client) -> the query of the client's page ("?level=<id>&mode=agent"), or None when not known at connect
        # (server.web.relay.page_query); then it comes with the /keys hello.
        self.page_query = page_query
        # (query) -> the level that address names (a gallery level, a draft), or None: drawn into the page itself
        # (`preview`), set by the gallery and drafts integrations (chained: the first that knows it answers).
        self.level_of_query: Callable[[str], object] | None = None
        self._lock = threading.Lock()
        self.sessions: dict[int, Session] = {}
        self.by_nonce: dict[str, Session] = {}
        self.rejected: set[int] = set()
        self._starting = 0
        self._gone: set[int] = set()
        server.on_client_connect(self._connect)
        server.on_client_disconnect(self._disconnect)

    def _warmup_progressed(self) -> None:
        """Redraw the tabs that show the warm-up's progress (on the warm-up thread)."""
        with self._lock:
            sessions = list(self.sessions.values())
        for session in sessions:
            session.refresh()

    def preparing(self) -> str | None:
        """"preparing the simulation: compiling size m: 2 of 5" while the server compiles, else None."""
        progress = None if self.warmup is None else self.warmup.progress()
        return None if progress is None else f"{PREPARING}: {progress}"

    @property
    def starting(self) -> int:
        """Sessions being built now: their tabs connected, they are not in `sessions` yet (or never will be, if the
        tab left meanwhile)."""
        with self._lock:
            return self._starting

    def _connect(self, client) -> None:
        with self._lock:  # reserve the slot now: sessions take a moment to build and connects can overlap
            full = len(self.sessions) + self._starting >= self.max_sessions
            if full:
                self.rejected.add(client.client_id)
            else:
                self._starting += 1
        if full:
            self._reject(client)
            return
        session = None
        query = self.page_query(client) if self.page_query is not None else None
        try:
            level = self.initial_level(client) if self.initial_level else None
            # A page whose address names a level (?level=, ?draft=) starts with it, so its first frame (sent before
            # the panel) shows that level, as the page does already (`preview`), not a new level until the address
            # is opened; opening it over the untouched start adds no undo step (server.editor.Editor.import_bytes).
            level = (self.level_named(query) if query else None) or level
            session = Session(client, self, level=level)
        except Exception:
            log.exception("could not start a session")
            client.gui.add_markdown("**Could not start a session.** See the server log.")
        finally:
            with self._lock:
                self._starting -= 1
                gone = client.client_id in self._gone  # the tab closed while its session was being built
                self._gone.discard(client.client_id)
                if session is not None and not gone:
                    self.sessions[client.client_id] = session
                    self.by_nonce[session.nonce] = session
            if session is not None and gone:
                session.close()
        if session is not None and not gone and query is not None:
            try:
                self.open_query(session, query)
            except Exception:  # a bug in a hook must not leave the tab half-opened without a word in the log
                log.exception("could not open %r in a new tab", query)

    def open_query(self, session: Session, query: str) -> None:
        """Open what the page's address names (on_query: `?level=<id>&mode=agent`, `?draft=<id>`), once per session:
        at connect when the relay passed the query on, else with the /keys hello, which also comes again after a
        network blip and must not reopen the level under the player. A second call waits for the first to finish
        (the /keys socket says "ready" only then, so keys pressed meanwhile act on the opened level)."""
        with session.query_lock:
            if session.query_opened:
                return
            session.query_opened = True
            if self.on_query is not None:
                self.on_query(session, query)

    def preview(self, query: str) -> bytes | None:
        """A JPEG of the level the address `query` names, drawn as a tab's first frame would be, for the page itself
        to show until its session's first frame arrives (server.web.http); None if it names none or cannot be drawn."""
        level_file = self.level_named(query)
        if level_file is None:
            return None
        try:
            return preview_jpeg(level_file.level)
        except Exception:  # the page must come anyway; its session draws (or refuses) the level itself
            log.exception("could not draw the preview of %r", query)
            return None

    def level_named(self, query: str):
        """The LevelFile the address `query` names (level_of_query), None if none; never raises: a level that no longer
        builds or a database hiccup only means the tab starts without it (opening the address then says why)."""
        if self.level_of_query is None or not query:
            return None
        try:
            return self.level_of_query(query)
        except Exception:
            log.warning("cannot find the level of %r", query, exc_info=True)
            return None

    def _reject(self, client) -> None:
        text = (f"**The server is full**: it allows {self.max_sessions} open tabs at a time. "
                "Close another tab (or start the server with a larger `--max-sessions`) and reload this page.")
        client.gui.add_markdown(text)
        client.add_notification("Server full", text.replace("**", ""), with_close_button=False, color="red")
        view = draw.View(640, 360)
        frame = draw.draw_frame(None, view, banner=f"Server full ({self.max_sessions} tabs)\nclose a tab and reload",
                                legend=False)
        client.scene.set_background_image(frame, format="jpeg")

    def _disconnect(self, client) -> None:
        with self._lock:
            was_rejected = client.client_id in self.rejected
            self.rejected.discard(client.client_id)
            session = self.sessions.pop(client.client_id, None)
            if session is not None:
                self.by_nonce.pop(session.nonce, None)
            elif self._starting and not was_rejected:
                self._gone.add(client.client_id)
        if session is not None:
            session.close()

    def add_listener(self, listener: PlayListener) -> None:
        self.listeners.append(listener)

    def notify(self, event: str, session: Session, *args) -> None:
        """Call `event` on every listener; a failing listener is logged and never breaks the play."""
        for listener in self.listeners:
            try:
                getattr(listener, event)(session, *args)
            except Exception:
                log.exception("play listener %s.%s failed", type(listener).__name__, event)

    def session_by_nonce(self, nonce: str) -> Session | None:
        with self._lock:
            return self.by_nonce.get(nonce)

    def close_all(self) -> None:
        with self._lock:
            sessions = list(self.sessions.values())
            self.sessions.clear()
            self.by_nonce.clear()
        for session in sessions:
            session.close()
        self.scheduler.close()
        self.encoder.shutdown(wait=True, cancel_futures=True)
