"""Every tab's work as a draft on the server, and an address bar that names what the tab has open.

`DraftLink(DraftStore(...)).attach(manager)` hooks a SessionManager:
- the page's address is `?level=<gallery id>` while the tab shows a gallery level as saved or opened, and
  `?draft=<id>` otherwise (a new level, or a gallery level edited since): the session puts it in a hidden
  `<div id="kinetix-address" data-query=...>` and static/keys.js shows it with history.replaceState;
- every edit (every change of the editor's undo history) queues the tab's draft: the level, the undo and redo
  stacks and the gallery level it came from (server.drafts.store writes it atomically on its own thread);
- the /keys hello carries the page's query, so a reload, a reopened link or a reconnect after a server restart
  with `?draft=<id>` reopens that draft, with its undo history;
- saving to the gallery discards the draft (the address becomes `?level=<new id>`), so does the tab's "Discard this
  draft" button (the tab starts a new level); old drafts expire (server.drafts.store.DRAFT_MAX_AGE_S, DRAFT_CAP).

No "leave this page?" prompt: an edit reaches the server before the next frame and the server writes it
whether or not the tab stays, and a "Save to gallery" runs to its end on the server even if the tab goes.
"""

from __future__ import annotations

import dataclasses
import html
import logging
import threading
from urllib.parse import parse_qs, urlencode

from server.drafts.store import DraftError, DraftStore, draft_document, snapshot_json, valid_id
from server.play.hooks import PlayListener

log = logging.getLogger(__name__)


def _address_html(query: str) -> str:
    return f'<div id="kinetix-address" data-query="{html.escape(query)}" hidden></div>'


def history_signature(editor) -> tuple:
    """Changes with every committed edit, undo and redo (not with a drag in progress or a tool change)."""
    undo, redo = editor.history.undo_stack, editor.history.redo_stack
    return len(undo), len(redo), id(undo[-1]) if undo else 0, id(redo[-1]) if redo else 0


@dataclasses.dataclass
class TabDraft:
    address: object  # the hidden GUI html element holding the address
    draft_id: str | None = None  # known once the page said hello
    gallery_seen: str | None = None  # the session's gallery_id as last seen
    clean: tuple | None = None  # the history signature while the tab shows a gallery level unedited
    queued: tuple | None = None  # the history signature of the last queued draft
    opening: bool = False  # while a link is opened: the edits that makes are not the user's
    shown: str = ""
    cache: dict = dataclasses.field(default_factory=dict)  # id(snapshot) -> (snapshot, its JSON), undo steps


class DraftLink(PlayListener):
    def __init__(self, store: DraftStore):
        self.store = store
        self._lock = threading.Lock()
        self._tabs: dict[object, TabDraft] = {}  # session -> its draft state; removed when the tab goes

    def attach(self, manager) -> None:
        previous, previous_level = manager.on_query, manager.level_of_query
        manager.add_listener(self)
        manager.on_query = lambda session, query: self.open_from_query(session, query, previous)
        manager.level_of_query = lambda query: self.level_of_query(query, previous_level)

    def level_of_query(self, query: str, previous=None):
        """The level `?draft=<id>` names (the page draws it before its session starts); else what `previous` (the
        gallery's) finds; None if neither knows it."""
        from kinetix.formats import build

        draft_id = (parse_qs(query.lstrip("?")).get("draft") or [None])[0]
        if draft_id is None:
            return previous(query) if previous is not None else None
        if not valid_id(draft_id):
            return None
        try:
            draft = self.store.load(draft_id)
        except DraftError:  # the tab says why once its session opens the address
            return None
        return None if draft is None else build(draft.spec, draft.size)

    def tab(self, session) -> TabDraft | None:
        with self._lock:
            return self._tabs.get(session)

    # ------------------------------------------------------------------ listener events

    def session_opened(self, session) -> None:
        if not hasattr(session.editor, "history"):  # a stand-in editor (play only, tests) has nothing to keep
            return
        gui = session.client.gui
        address = gui.add_html(_address_html(""))
        with gui.add_folder("Draft", expand_by_default=False):
            gui.add_markdown("This tab's work is kept on the server as a draft, with its undo history, so a reload "
                             "or the link in the address bar brings it back.")
            discard = gui.add_button("Discard this draft")
        discard.on_click(lambda _event: self.discard(session))
        with self._lock:
            self._tabs[session] = TabDraft(address=address)

    def session_closed(self, session) -> None:
        with self._lock:
            self._tabs.pop(session, None)  # a queued draft is still written

    def level_changed(self, session) -> None:
        tab = self.tab(session)
        if tab is None or tab.opening or tab.draft_id is None:
            return
        with session.lock:
            signature = history_signature(session.editor)
            if session.gallery_id != tab.gallery_seen:  # opened from the gallery, or saved to it
                tab.gallery_seen = session.gallery_id
                if session.gallery_id is not None:
                    tab.clean, tab.queued = signature, None
                    self.store.discard(tab.draft_id)  # saved or replaced: the gallery level is what is open
                    self._show(tab, "?" + urlencode({"level": session.gallery_id}))
                    return
            if tab.clean is not None:
                if signature == tab.clean:
                    return
                tab.clean = None  # edited: from now on the tab's work is a draft
            if signature == tab.queued:
                return
            tab.queued = signature
            self.store.save_later(tab.draft_id, self._document(session, tab))
            self._show(tab, "?" + urlencode({"draft": tab.draft_id}))

    # ------------------------------------------------------------------ opening from the page's address

    def open_from_query(self, session, query: str, previous=None) -> None:
        """The /keys hello: `?draft=<id>` reopens that draft; anything else goes on to the gallery and agents."""
        tab = self.tab(session)
        if tab is None:
            if previous is not None:
                previous(session, query)
            return
        params = parse_qs(query.lstrip("?"))
        draft_id = (params.get("draft") or [None])[0]
        if draft_id is not None:
            if self._reopen(session, tab, draft_id):
                return
        else:
            tab.opening = True
            try:
                if previous is not None:
                    previous(session, query)
            finally:
                tab.opening = False
        with session.lock:
            tab.gallery_seen = session.gallery_id
            tab.draft_id = tab.draft_id or self.store.new_id()
            if session.gallery_id is not None and session.gallery_id == (params.get("level") or [None])[0]:
                tab.clean = history_signature(session.editor)  # the link names it already
            else:
                tab.clean = None
                self._show(tab, "?" + urlencode({"draft": tab.draft_id}))

    def _reopen(self, session, tab: TabDraft, draft_id: str) -> bool:
        """Load draft `draft_id` into the tab; False (and a new draft id, with a notice) when it cannot be."""
        if not valid_id(draft_id):
            self._notify(session, "Not a draft", f"{draft_id!r} is not a draft id; this is a new draft.")
            return False
        try:
            draft = self.store.load(draft_id)
        except DraftError as error:
            log.warning("%s", error)
            self._notify(session, "Could not reopen the draft", f"{error}. This is a new draft; the old file is "
                         "left on the server.")
            return False
        with session.lock:
            tab.draft_id = draft_id  # a draft never edited has no file yet: the tab goes on with this id
            if draft is not None:
                try:
                    session.stop()
                    session.editor.load_draft(draft.spec, draft.size, draft.undo, draft.redo)
                except (ValueError, TypeError) as error:  # a level that no longer builds (LevelError is one)
                    tab.draft_id = None
                    self._notify(session, "Could not reopen the draft", f"draft {draft_id}: {error}")
                    return False
                tab.gallery_seen, tab.clean, tab.queued = draft.gallery_id, None, history_signature(session.editor)
                session.gallery_id = draft.gallery_id  # a later save is a remix of it
                if session.panel is not None and hasattr(session.panel, "refresh"):
                    session.panel.refresh()
                session.refresh(force=True)
            else:
                tab.gallery_seen, tab.clean = session.gallery_id, None
            self._show(tab, "?" + urlencode({"draft": draft_id}))
        return True

    def discard(self, session) -> None:
        """Throw the tab's draft away: the file goes, the tab starts a new level (no undo) under a new draft id."""
        from server.editor.levelio import new_level

        tab = self.tab(session)
        if tab is None or tab.draft_id is None:
            return
        with session.lock:
            self.store.discard(tab.draft_id)
            session.stop()
            size = session.editor.size
            session.editor.load_draft(new_level(size), size, [], [])
            tab.draft_id, tab.gallery_seen, tab.clean = self.store.new_id(), None, None
            tab.queued = history_signature(session.editor)  # nothing to keep until the next edit
            session.gallery_id = None
            if session.panel is not None and hasattr(session.panel, "refresh"):
                session.panel.refresh()
            session.refresh(force=True)
            self._show(tab, "?" + urlencode({"draft": tab.draft_id}))

    # ------------------------------------------------------------------ helpers

    def _document(self, session, tab: TabDraft) -> dict:
        """The draft of the tab now (under its lock). Undo steps never change, so each is converted once."""
        editor = session.editor
        cache: dict = {}

        def convert(snapshot) -> dict:
            entry = tab.cache.get(id(snapshot))
            if entry is None or entry[0] is not snapshot:
                entry = (snapshot, snapshot_json(snapshot.spec, snapshot.size))
            cache[id(snapshot)] = entry
            return entry[1]

        undo = [convert(s) for s in editor.history.undo_stack]
        redo = [convert(s) for s in editor.history.redo_stack]
        tab.cache = cache
        return draft_document(snapshot_json(editor.spec, editor.size), undo, redo, session.gallery_id)

    def _show(self, tab: TabDraft, query: str) -> None:
        if query != tab.shown:
            tab.shown = query
            tab.address.content = _address_html(query)

    @staticmethod
    def _notify(session, title: str, body: str) -> None:
        try:
            session.client.add_notification(title, body, color="red", auto_close_seconds=12.0)
        except Exception:  # the tab went away meanwhile
            log.debug("notification not shown", exc_info=True)
