"""The SessionManager: every tab's Session, created on viser's connect and closed on disconnect, capped at
--max-sessions; the one play thread (server.play.scheduler), the frame encoders and the listeners they share."""

from __future__ import annotations

import concurrent.futures
import logging
import threading
from collections.abc import Callable

from server.play import draw
from server.play.hooks import PlayListener
from server.play.scheduler import PlayScheduler
from server.play.session import Session
from server.play.warmup import PREPARING

log = logging.getLogger(__name__)


class SessionManager:
    """All sessions of one server: created on viser connect, removed on disconnect, capped at `max_sessions`."""

    def __init__(self, server, *, max_sessions: int = 8, initial_level: Callable | None = None,
                 editor_factory: Callable | None = None, warmup=None):
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
        self.initial_level = initial_level  # (client) -> LevelFile | None, e.g. from ?level= (gallery)
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
        try:
            level = self.initial_level(client) if self.initial_level else None
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
