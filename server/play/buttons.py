"""The tab's Play folder: Play / Start / Stop (Space), Pause / Resume, Step, Play again and Edit, whose labels and
states follow the session's mode."""

from __future__ import annotations

from typing import Protocol


class PlayControls(Protocol):
    """What the Play folder's buttons drive (a Session is one): the folder never needs the whole session."""

    def toggle_play(self) -> None: ...

    def toggle_pause(self) -> None: ...

    def single_step(self) -> None: ...

    def play_again(self) -> None: ...

    def stop(self) -> None: ...


class PlayButtons:
    def __init__(self, gui, session: PlayControls):
        with gui.add_folder("Play"):
            self.play = gui.add_button("Play (Space)", icon=None)
            self.pause = gui.add_button("Pause", disabled=True)
            self.step = gui.add_button("Step", disabled=True)
            self.again = gui.add_button("Play again", visible=False)
            self.edit = gui.add_button("Edit", visible=False)
        self.play.on_click(lambda _: session.toggle_play())
        self.pause.on_click(lambda _: session.toggle_pause())
        self.step.on_click(lambda _: session.single_step())
        self.again.on_click(lambda _: session.play_again())
        self.edit.on_click(lambda _: session.stop())

    def update(self, mode: str) -> None:
        """Labels and states for this mode ("edit" | "ready" | "play" | "paused" | "ended" | "replay")."""
        self.play.label = "Play (Space)" if mode == "edit" else "Start (Space)" if mode == "ready" else "Stop (Space)"
        self.play.visible = mode != "ended"  # an ended play has nothing to stop: Play again or Edit (Space: Edit)
        self.pause.disabled = mode not in ("play", "paused")
        self.pause.label = "Resume" if mode == "paused" else "Pause"
        self.step.disabled = mode not in ("play", "paused", "ready")
        self.again.visible = mode == "ended"
        self.edit.visible = mode in ("ended", "ready")
