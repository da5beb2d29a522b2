"""The gallery inside an editor tab: Save to gallery, Open from gallery, `/?level=<id>` links and play records.

`GalleryLink(store).attach(manager)` hooks a SessionManager:
- every new session gets a "Gallery" folder with Save (a modal for name, description and tags) and Open (a modal
  listing the newest levels), plus a link to the /gallery page;
- `/?level=<id>` opens that level in the tab (`&mode=play` opens it for play: it starts on Space or the first
  control key); the page's query reaches Python through the /keys hello;
- every finished play of a level that is in the gallery is recorded (solved, steps, seconds of simulated time, so
  pauses and a slow machine do not change a player's time), as kind "agent" when an agent played it; with the
  server's PlayRecorder, a human solve that beats the level's best and whose recording verifies by replay sets
  the best time and keeps its recording (server.gallery.runs; without one it sets no best time);
- `/?level=<id>&mode=replay` replays the level's best run (server.recordings.replay).

A save made while editing a gallery level is a remix: it keeps that level as its parent. The author token comes
from the browser's localStorage (sent with the /keys hello); a save that issues a new token hands it back to the
page, which keeps it for the gallery page too.
"""

from __future__ import annotations

import html
import json
import logging
from collections.abc import Callable
from urllib.parse import parse_qs

from server.gallery.checks import StoreError
from server.gallery.runs import BestRuns
from server.gallery.store import Store

log = logging.getLogger(__name__)

OPEN_LIST_SIZE = 50  # levels offered by "Open from gallery" (newest first); the gallery page shows them all


class GalleryLink:
    def __init__(self, store: Store, recorder=None, open_replay: Callable[..., bool] | None = None):
        self.store = store
        # `open_replay(session, path, title)` replays a recording in the tab (server.recordings.replay.open_best_run,
        # given by server.app: recordings build on play, so play does not import them); None: no replays.
        self.open_replay = open_replay
        # With the server's PlayRecorder, the best human solve of each level keeps its recording (runs.BestRuns);
        # without it (kinetix serve --no-record) the kept best runs can still be replayed.
        self.recorder = recorder
        self.runs = BestRuns(store) if store.recordings_dir is not None else None

    def attach(self, manager) -> None:
        manager.on_session_gui = self.build_gui
        manager.on_query = self.open_from_query
        manager.on_play_end = self.record_play
        manager.level_of_query = self.level_of_query

    # ------------------------------------------------------------------ GUI

    def build_gui(self, session) -> None:
        gui = session.client.gui
        with gui.add_folder("Gallery"):
            save = gui.add_button("Save to gallery")
            open_ = gui.add_button("Open from gallery")
            gui.add_markdown("[Browse the gallery](gallery)")  # relative: also under --root-path
        save.on_click(lambda event: self._save_modal(session))
        open_.on_click(lambda event: self._open_modal(session))

    def _save_modal(self, session) -> None:
        gui = session.client.gui
        with gui.add_modal("Save to gallery") as modal:
            name = gui.add_text("Name", initial_value=session.editor.spec.name or "")
            description = gui.add_text("Description", initial_value="", multiline=True)
            tags = gui.add_text("Tags (comma-separated)", initial_value="")
            status = gui.add_markdown("")
            save = gui.add_button("Save")
            cancel = gui.add_button("Cancel")

        def on_save(_event) -> None:
            tag_list = [t.strip() for t in tags.value.split(",") if t.strip()]
            try:
                level_id = self.save(session, name.value, description.value, tag_list)
            except StoreError as error:
                status.content = f"**Not saved:** {html.escape(str(error))}"
                return
            modal.close()
            session.client.add_notification("Saved to the gallery", f"Share it: /?level={level_id}",
                                            auto_close_seconds=8.0)

        save.on_click(on_save)
        cancel.on_click(lambda _event: modal.close())

    def _open_modal(self, session) -> None:
        gui = session.client.gui
        items, _ = self.store.list_levels(sort="newest", limit=OPEN_LIST_SIZE)
        with gui.add_modal("Open from gallery") as modal:
            if not items:
                gui.add_markdown("The gallery is empty.")
                gui.add_button("Close").on_click(lambda _event: modal.close())
                return
            labels = [f"{item['name']} ({item['size']}, {item['id']})" for item in items]
            choice = gui.add_dropdown("Level", options=labels, initial_value=labels[0])
            status = gui.add_markdown("")
            open_ = gui.add_button("Open")
            cancel = gui.add_button("Cancel")

        def on_open(_event) -> None:
            level_id = items[labels.index(choice.value)]["id"]
            try:
                self.open(session, level_id)
            except (StoreError, ValueError) as error:
                status.content = f"**Cannot open:** {html.escape(str(error))}"
                return
            modal.close()

        open_.on_click(on_open)
        cancel.on_click(lambda _event: modal.close())

    # ------------------------------------------------------------------ actions (also the tests' entry points)

    def save(self, session, name: str, description: str = "", tags: list[str] | None = None) -> str:
        """Save the tab's level as the tab's identity; returns the new level's id. A stale author token is replaced
        by a new identity, which the tab then keeps (`identity`)."""
        document = json.loads(session.editor.export("ours"))
        kwargs = dict(description=description, tags=tags or [], parent=session.gallery_id)
        level_id, _ = self.store.create_level(name, document, token=self.identity(session), **kwargs)
        session.gallery_id = level_id
        return level_id

    def identity(self, session) -> str:
        """The tab's gallery identity (author token): the one it has if this gallery knows it, else a new one, kept
        by the session and handed to the page (keys.js puts it in localStorage, where the gallery page and the next
        session of this tab find it). One identity per tab: its saves, its plays and so its votes."""
        token, new = self.store.identity(session.author_token)
        if new:
            session.author_token = token
            client = session.client
            if client is None:  # the tab closed meanwhile (a play recorded after the disconnect): nobody to tell
                return token
            # keys.js copies it into localStorage, where the gallery page finds it too.
            client.gui.add_html(f'<div id="kinetix-token" data-token="{html.escape(token)}" hidden></div>')
        return token

    def open(self, session, level_id: str) -> None:
        """Load a gallery level into the tab for editing (a later save is a remix of it)."""
        level = self.store.get_level(level_id)
        session.open_level(json.dumps(level["level"]).encode(), f"{level_id}.json")
        session.gallery_id = level_id

    def level_of_query(self, query: str):
        """The LevelFile `?level=<id>` names (the page draws it before its session starts), None if none or unknown."""
        from kinetix.levels import load_level

        level_id = (parse_qs(query.lstrip("?")).get("level") or [None])[0]
        if not level_id:
            return None
        try:
            return load_level(self.store.get_level(level_id)["level"])
        except StoreError:  # not in the gallery: the tab says so once its session opens the address
            return None

    def open_from_query(self, session, query: str) -> None:
        """`?level=<id>[&mode=play]` from the page URL."""
        params = parse_qs(query.lstrip("?"))
        level_id = (params.get("level") or [None])[0]
        if not level_id:
            return
        try:
            self.open(session, level_id)
        except (StoreError, ValueError) as error:
            session.client.add_notification("Cannot open that level", str(error), color="red")
            return
        mode = (params.get("mode") or [""])[0]
        if mode == "play":
            session.play(wait=True)  # the player starts it with Space or the first control key
        elif mode == "replay":
            self.replay_best_run(session, level_id)

    def replay_best_run(self, session, level_id: str) -> bool:
        """Replay the level's best run in the tab (`?level=<id>&mode=replay`); a notification if it has none."""
        path = self.runs.best_run_file(level_id) if self.runs is not None else None
        if path is None or self.open_replay is None:
            session.client.add_notification("No best run yet", "Nobody has solved this level with a recording yet: "
                                            "play it!", color="yellow")
            return False
        return self.open_replay(session, path, f"the best run of {session.editor.spec.name or level_id}")

    def record_play(self, session, result: str, steps: int, seconds: float) -> None:
        if session.gallery_id is None:  # an unsaved level has no gallery entry to count the play against
            return
        level_id = session.gallery_id
        # "human", "agent:<name>" (Watch agent) or e.g. "race" (a race records its own two plays)
        player = getattr(session, "ended_player", session.player)
        kind = "human" if player == "human" else "agent" if player.startswith("agent") else None
        if kind is None:
            return
        best = self.runs.candidate(self.recorder, session, result, steps, seconds) if self.runs else None
        try:
            # A human play makes the tab's identity one that may vote on this level (Store.vote).
            self.store.record_play(level_id, kind, solved=result == "solved", steps=int(steps),
                                   seconds=float(seconds), recording_path=best,
                                   author=self.identity(session) if kind == "human" else None)
        except StoreError as error:  # e.g. the level was deleted meanwhile; a lost statistic is not worth a crash
            log.warning("play not recorded for %s: %s", level_id, error)
            if best is not None:
                self.runs.discard(best)
            return
        if best is not None:
            self.runs.prune(level_id)  # the previous best run's file goes
