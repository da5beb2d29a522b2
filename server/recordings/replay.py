"""Recordings in the tab: download the current or last play, and replay any recording with a timeline.

`RecordingPanel(recorder)` is a session.PlayListener; on every new session it adds a "Recordings" folder:
- **Download recording**: the play running now (its steps so far, as a complete file; see
  PlayRecorder.download) or else the tab's last play, as an .mcap file;
- **Replay last play** and **Replay a file (.mcap)** (an upload): open a `Replay`;
- a status line for what went wrong (a bad upload: not MCAP, not ours, truncated, too large).

A `Replay` puts the session in mode "replay" (no editing, no play) and draws, with server.play.draw, the scene of
kinetix.recording.recorded_level(recording, step): the recorded states, no re-simulation (and no JAX call per
frame: Replay.scene_at sets the recorded positions and angles in numpy), so scrubbing to any step is immediate.
Its timeline ("Replay" folder, at the top of the panel while a replay is open): Play/Pause, a "Replay step"
slider (scrub), Speed, Close replay. The slider counts steps done, 0 (the start) to N (after the last of N
steps), as the HUD's "step k/N" does. ←/→ step back and forward (Shift: 10 steps), pausing the replay; they work
with the slider focused or not (keys reach the session through keys.js). Space, Esc, Play or Close replay leave
it. A thread per replay advances the step at the recorded pace times the speed.

`open_best_run(session, path, title)` is what `/?level=<id>&mode=replay` calls (server.play.gallery_tab).
"""

from __future__ import annotations

import dataclasses
import html
import logging
import math
import threading
import time
from pathlib import Path

from kinetix.recording import Recording, RecordingError, read_recording, recorded_level
from server.play import draw
from server.play.hooks import PlayListener
from server.play.session import Session

log = logging.getLogger(__name__)

MAX_UPLOAD = 200 * 1024 * 1024  # bytes; a 10-minute play with frames is a few MB
SPEEDS = {"0.25x": 0.25, "0.5x": 0.5, "1x": 1.0, "2x": 2.0, "4x": 4.0}
FRAME_S = 1.0 / 30  # the replay pushes at most 30 frames a second
PAUSED_LOOK_S = 0.25  # while paused, how often the thread looks for a resized canvas
SLIDER_EVERY_S = 0.1  # while playing, the slider follows at this pace (each move is a message to the tab)
RESULT_TEXT = {"solved": "Solved", "failed": "Failed", "truncated": "Time is up", "nan": "The simulation broke"}
STEP_KEYS = {"ArrowLeft": -1, "ArrowRight": 1}  # key code -> steps; Shift makes it SHIFT_STEPS steps
SHIFT_STEPS = 10
TIMELINE_ORDER = -1.0  # viser orders panel items by this (its default counter starts at 1): the timeline comes first


def step_seconds(recording: Recording) -> float:
    """Simulated seconds per recorded step; RecordingError for a file whose env description does not say."""
    try:
        seconds = float(recording.env["params"]["sim"]["dt"]) * int(recording.env["frame_skip"])
    except (KeyError, TypeError, ValueError) as error:
        raise RecordingError(f"the recording's env description has no usable time step ({error})") from None
    if not math.isfinite(seconds) or seconds <= 0:
        raise RecordingError(f"the recording's time step {seconds} is not a positive number")
    return seconds


def outcome(recording: Recording) -> str:
    """What the recording's first episode came to ("" while it had not ended)."""
    for i in range(recording.num_steps):
        if recording.terminated[i]:
            return "solved" if recording.rewards[i] > 0.5 else "failed" if recording.rewards[i] < -0.5 else "nan"
        if recording.truncated[i]:
            return "truncated"
    return ""


class Replay:
    """One recording shown in one tab: the timeline state and the thread that pushes its frames."""

    def __init__(self, session: Session, panel: SessionPanel, recording: Recording, title: str):
        self.session, self.panel, self.recording, self.title = session, panel, recording, title
        self.tick = step_seconds(recording)
        self.last = recording.num_steps - 1  # the last step; -1 is the start, before any step
        self.position = -1.0  # the current step, fractional while playing
        self.speed = 1.0
        self.playing = False
        self.shown_step: int | None = None  # the step of the last frame pushed (tests and the HUD)
        self.frames_pushed = 0
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._wake = threading.Event()
        self._dirty = True
        self._stopping = False
        self._scene: draw.Scene | None = None  # the last scene drawn
        self._base: draw.Scene | None = None  # the recording's starting scene (static parts shared by every step)
        self._canvas: draw.View | None = None
        self._result = outcome(recording)
        self._thread = threading.Thread(target=self._run, name="kinetix-replay", daemon=True)

    # ------------------------------------------------------------------ control (GUI callbacks, tests)

    @property
    def step(self) -> int:
        with self._lock:
            return math.floor(self.position)  # -0.5 is still the start (-1), not step 0

    def start(self) -> None:
        session = self.session
        with session.lock:
            if session.closed:
                return
            session.stop()  # ends a play, or an earlier replay
            session.mode = "replay"
            session.replay = self
            session.set_buttons()
        self._thread.start()

    def stop(self) -> None:
        """The session left the replay (or closed); the thread ends at its next look. Waits at most for one frame
        being sent (the sender never takes the session's lock, which the caller may hold)."""
        self._stopping = True
        self._wake.set()
        with self._send_lock:
            pass
        self.panel.replay_ended(self)

    def set_playing(self, playing: bool) -> None:
        with self._lock:
            if playing and self.position >= self.last:  # Play at the end starts over
                self.position = -1.0
            self.playing = playing
            self._dirty = True
        self._wake.set()

    def seek(self, step: int) -> None:
        with self._lock:
            self.position = float(min(max(int(step), -1), self.last))
            self._dirty = True
        self._wake.set()

    def step_by(self, steps: int) -> None:
        """Pause and move `steps` steps back (negative) or forward from the step shown, within the recording."""
        with self._lock:
            self.playing = False
            self.position = float(min(max(math.floor(self.position) + int(steps), -1), self.last))
            self._dirty = True
        self._wake.set()

    def on_key(self, code: str, shift: bool = False) -> bool:
        """A keydown in the replaying tab (Session.key_event): ←/→ step; True if the key was used."""
        if code not in STEP_KEYS:
            return False
        self.step_by(STEP_KEYS[code] * (SHIFT_STEPS if shift else 1))
        return True

    def set_speed(self, speed: float) -> None:
        with self._lock:
            self.speed = float(speed)
            self._dirty = True
        self._wake.set()

    # ------------------------------------------------------------------ the replay thread

    def _run(self) -> None:
        try:
            self._loop()
        except Exception:  # e.g. the tab went away between two looks; a replay must not die with a traceback
            if not self._stopping and not self.session.closed:
                log.exception("replay stopped")

    def _loop(self) -> None:
        before = time.perf_counter()
        last_slider = 0.0
        while not self._stopping:
            now = time.perf_counter()
            with self._lock:
                if self.playing:
                    self.position = min(self.position + (now - before) * self.speed / self.tick, float(self.last))
                    if self.position >= self.last:
                        self.playing = False
                    self._dirty = True
                step, dirty, playing = math.floor(self.position), self._dirty, self.playing
                self._dirty = False
            before = now
            canvas = self.session.canvas() if self.session.client is not None else None
            if canvas != self._canvas:  # the tab was resized: redraw even while paused
                self._canvas, dirty = canvas, True
            if dirty:
                try:
                    self._push(step)
                except Exception:  # a drawing bug must not kill the thread silently mid-replay
                    log.exception("replay frame failed")
                if not playing or now - last_slider >= SLIDER_EVERY_S:
                    last_slider = now
                    self.panel.show_step(self, step, playing)
            self._wake.wait(FRAME_S if playing else PAUSED_LOOK_S)
            self._wake.clear()

    def scene_at(self, step: int) -> draw.Scene:
        """The drawn scene after `step`: kinetix.recording.recorded_level's state, built in numpy. Only positions
        and angles differ between steps (draw.scene_of(static_from=...) relies on the same), and no JAX call per
        frame means no compile on the first frame and no dispatch cost while scrubbing."""
        if self._base is None:
            self._base = draw.scene_of(recorded_level(self.recording, -1))
        if step < 0:
            return self._base
        position, angle = self._base.position.copy(), self._base.angle.copy()
        position[self.recording.bodies] = self.recording.position[step]
        angle[self.recording.bodies] = self.recording.rotation[step]
        return dataclasses.replace(self._base, position=position, angle=angle)

    def _push(self, step: int) -> None:
        session = self.session
        if session.closed or session.client is None:
            return
        self._scene = self.scene_at(step)
        meta = self.recording.metadata
        hud = (f"REPLAY  {meta.get('player', '?')}  step {step + 1}/{self.last + 1}  "
               f"{(step + 1) * self.tick:.2f} s  {self.speed:g}x  Space: back to editing")
        banner = ""
        if step == self.last and self._result:
            banner = f"{RESULT_TEXT[self._result]}\n{(step + 1) * self.tick:.2f} s, {step + 1} steps"
        frame = draw.draw_frame(self._scene, session.canvas(), hud=hud, banner=banner)
        with self._send_lock:  # stop() waits for a send in progress, so no replay frame lands after the edit frame
            if self._stopping:
                return
            session._send_frame(frame, None, False)  # not a play frame: no listener records it
            self.shown_step = step
            self.frames_pushed += 1


class SessionPanel:
    """The "Recordings" and "Replay" folders of one tab."""

    def __init__(self, owner: RecordingPanel, session: Session):
        self.owner, self.session = owner, session
        self.replay: Replay | None = None
        self._setting = False  # True while the server moves the slider (its callback must not seek)
        gui = session.client.gui
        with gui.add_folder("Recordings"):
            self.download_button = gui.add_button("Download recording")
            self.replay_last_button = gui.add_button("Replay last play")
            self.upload = gui.add_upload_button("Replay a file (.mcap)", mime_type=".mcap,application/octet-stream")
            self.status = gui.add_markdown("")
        # Made visible (and opened) when a replay starts; at the top, not below the editor's long panel.
        with gui.add_folder("Replay", visible=False, order=TIMELINE_ORDER) as self.timeline:
            self.title = gui.add_markdown("")
            self.play_button = gui.add_button("Play replay")
            # Steps done: 0 is the start, N the end of an N-step recording (Replay.step + 1).
            self.slider = gui.add_slider("Replay step", min=0, max=1, step=1, initial_value=0,
                                         hint="←/→ step back/forward (Shift: 10 steps)")
            self.speed = gui.add_dropdown("Speed", options=list(SPEEDS), initial_value="1x")
            self.close_button = gui.add_button("Close replay")
        self.download_button.on_click(lambda _: self.download())
        self.replay_last_button.on_click(lambda _: self.replay_last())
        self.upload.on_upload(lambda event: self.open_upload(event.target.value.name, event.target.value.content))
        self.play_button.on_click(lambda _: self._toggle())
        self.slider.on_update(lambda _: self._scrub())
        self.speed.on_update(lambda _: self.replay and self.replay.set_speed(SPEEDS[self.speed.value]))
        self.close_button.on_click(lambda _: self.session.stop())

    def say(self, text: str, error: bool = False) -> None:
        self.status.content = text
        if error:
            self.session.client.add_notification("Recording", text.replace("**", ""), color="red",
                                                 auto_close_seconds=10.0)

    # ------------------------------------------------------------------ buttons

    def download(self) -> None:
        try:
            found = self.owner.recorder.download(self.session)
        except (RecordingError, OSError) as error:
            self.say(f"**No download:** {html.escape(str(error))}", error=True)
            return
        if found is None:
            self.say("Nothing recorded yet: play first (Space).")
            return
        name, data = found
        self.session.client.send_file_download(name, data, save_immediately=True)
        self.say(f"Sent {html.escape(name)} ({len(data) // 1024 + 1} KB).")

    def replay_last(self) -> None:
        finished = self.owner.recorder.last_finished(self.session, timeout=10.0)
        if finished is None or finished.path is None:
            self.say("No finished play to replay yet: play first (Space), then stop.")
            return
        self.open_file(finished.path, "your last play")

    def open_upload(self, name: str, content: bytes) -> bool:
        """Replay an uploaded file; a bad one gets a clear message and leaves the tab as it was."""
        if len(content) > MAX_UPLOAD:
            self.say(f"**Cannot replay {html.escape(name)}:** it is {len(content) // 2**20} MB, at most "
                     f"{MAX_UPLOAD // 2**20} MB allowed", error=True)
            return False
        return self.open_bytes(content, name)

    def open_file(self, path: Path, title: str) -> bool:
        try:
            data = Path(path).read_bytes()
        except OSError as error:
            self.say(f"**Cannot replay {html.escape(title)}:** {html.escape(error.strerror or str(error))}",
                     error=True)
            return False
        return self.open_bytes(data, title)

    def open_bytes(self, data: bytes, title: str) -> bool:
        try:
            recording = read_recording(data, frames=False)
            step_seconds(recording)
        except RecordingError as error:
            message = str(error).replace("the recording", title, 1)
            self.say(f"**Cannot replay {html.escape(title)}:** {html.escape(message)}", error=True)
            return False
        replay = Replay(self.session, self, recording, title)
        self.replay = replay
        self.title.content = (f"**{html.escape(title)}**: {html.escape(recording.metadata.get('player', '?'))}, "
                              f"{recording.num_steps} steps")
        self._set_slider(0, max_value=max(recording.num_steps, 1))
        self.speed.value = "1x"
        self.play_button.label = "Pause replay"
        self.timeline.visible = True
        self.say(f"Replaying {html.escape(title)}.")
        replay.start()
        replay.set_playing(True)
        return True

    # ------------------------------------------------------------------ timeline

    def _toggle(self) -> None:
        replay = self.replay
        if replay is not None:
            replay.set_playing(not replay.playing)
            self.play_button.label = "Pause replay" if replay.playing else "Play replay"

    def _scrub(self) -> None:
        if self._setting or self.replay is None:
            return
        self.replay.seek(int(self.slider.value) - 1)  # the slider counts steps done; seek takes the step index

    def _set_slider(self, value: int, max_value: int | None = None) -> None:
        """Move the slider (steps done, 0..N) without seeking."""
        self._setting = True
        try:
            if max_value is not None:
                self.slider.max = max_value
            self.slider.value = value
        finally:
            self._setting = False

    def show_step(self, replay: Replay, step: int, playing: bool) -> None:
        """Called by the replay thread: the slider and the Play button follow the replay."""
        if replay is not self.replay or self.session.closed:
            return
        try:
            self._set_slider(step + 1)
            self.play_button.label = "Pause replay" if playing else "Play replay"
        except Exception:  # the tab went away meanwhile
            log.debug("timeline not updated", exc_info=True)

    def replay_ended(self, replay: Replay) -> None:
        if replay is self.replay:
            self.replay = None
            if self.session.closed:  # the tab is gone: nothing to hide
                return
            try:
                self.timeline.visible = False
            except Exception:
                log.debug("timeline not hidden", exc_info=True)


class RecordingPanel(PlayListener):
    """Adds the Recordings/Replay folders to every session (see the module docstring)."""

    def __init__(self, recorder):
        self.recorder = recorder  # server.recordings.recorder.PlayRecorder
        self.panels: dict[int, SessionPanel] = {}

    def session_opened(self, session: Session) -> None:
        self.panels[id(session)] = SessionPanel(self, session)

    def session_closed(self, session: Session) -> None:
        self.panels.pop(id(session), None)

    def panel(self, session: Session) -> SessionPanel | None:
        return self.panels.get(id(session))


def open_best_run(session: Session, path: Path, title: str) -> bool:
    """Replay a file in this tab (the gallery's `/?level=<id>&mode=replay`); False (with a message) if it fails."""
    panels = [listener for listener in session.manager.listeners if isinstance(listener, RecordingPanel)]
    panel = panels[0].panel(session) if panels else None
    if panel is None:
        session.client.add_notification("Cannot replay", "this server runs without recordings", color="red")
        return False
    return panel.open_file(path, title)
