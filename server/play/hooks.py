"""What other parts plug into a session: PlayListener (told about every play: recordings, drafts, the gallery, agent
overlays) and Controller (chooses the actions instead of the keyboard: agents). server.play.session calls them."""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from server.play import draw


class Tab(Protocol):
    """A tab's session as listeners and controllers see it (server.play.session.Session is one). Named here so this
    module does not import the session, which imports it."""

    client: Any  # viser's ClientHandle (None once the tab is gone)
    editor: Any  # the tab's editor (server.editor.Editor or a play-only stand-in)
    lock: Any  # the session's threading.RLock: listeners run holding it
    mode: str  # "edit" | "ready" | "play" | "paused" | "ended" | "replay"
    controller: Controller | None
    gallery_id: str | None

    @property
    def player(self) -> str: ...


def episode_end(result) -> str | None:
    """How a step ended its episode ("solved" | "failed" | "truncated" | "nan"), or None if it goes on."""
    if not (result.terminated or result.truncated):
        return None
    return "solved" if result.solved else "failed" if result.failed else "truncated" if result.truncated else "nan"


class PlayListener:
    """Told about every play of every session (recordings, agent overlays); add with SessionManager.add_listener.

    play_started, play_stepped and play_ended run with the session's lock held (on the play thread, or the
    caller's for play_started); frame_pushed runs on an encoder thread. All must be quick and must not block:
    hand heavy work to a thread. Override what you need.
    """

    def play_started(self, session: Tab, level_file, params) -> None:
        """A play began from `level_file` (the edited level, or the opened one) with these env params."""

    def play_stepped(self, session: Tab, action: np.ndarray, state, result) -> None:
        """One agent step was taken: the action used, the env state after it and its play.StepResult."""

    def frame_pushed(self, session: Tab, jpeg: bytes, frame: np.ndarray) -> None:
        """A play frame (not an edit frame) went to the tab: its JPEG bytes and RGB pixels.

        Runs on an encoder thread without the session's lock (frames are encoded in parallel with play)."""

    def play_ended(self, session: Tab, result: str, steps: int, seconds: float) -> None:
        """The episode ended ("solved" | "failed" | "truncated" | "nan"), or was stopped ("stopped")."""

    def level_changed(self, session: Tab) -> None:
        """The edited level or its undo history may have changed (after an edit-mode frame, and when the tab's
        gallery level changes); runs with the session's lock held. server.drafts.tab keeps drafts with it."""

    def session_opened(self, session: Tab) -> None:
        """A tab's session was built (its GUI exists): add per-tab GUI here (e.g. server.recordings.replay's panel)."""

    def session_closed(self, session: Tab) -> None:
        """The tab went away (a running play was ended as "stopped" just before)."""


class Controller:
    """Chooses actions instead of the keyboard while it is set on a playing session (e.g. an agent)."""

    player = "agent"  # who plays, as play records and recordings name it

    def act(self, state, params) -> np.ndarray:
        """The multi-discrete action (as play.action_from_keys returns) for this env state."""
        raise NotImplementedError

    def hud(self) -> str:
        """Extra text for the play HUD (e.g. the action per binding and the value estimate); '' for none."""
        return ""

    def episode_end(self, state, result) -> str | None:
        """After each step: the play's result if it is over now, else None (a race decides for both sides)."""
        return episode_end(result)

    def draw(self, session: Tab, view: draw.View, banner: str) -> np.ndarray | None:
        """A play frame of its own (e.g. an overlay, a race's two halves), or None for the usual one."""
        return None
