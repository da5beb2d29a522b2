"""One session per browser tab: its editor, play state and lock (server.play.manager owns them).

Threading: viser runs plain callbacks on a thread pool and they can overlap, so every entry point takes the
session's lock. Playing sessions are stepped and drawn by the manager's one play thread (server.play.scheduler),
which batches sessions that are due together. Key events arrive from the side server's event loop
(`key_event`), update the held-key set and wake the play thread at once; it steps that session and pushes a
frame right away and then flushes, so a key reaches the wire within a few milliseconds instead of waiting for
the next tick.

Frames: rendered by server.play.draw at the canvas size (letterboxed, never stretched) and pushed as the scene
background (JPEG). While playing: every agent step (30 per second for the default dt 1/60 and frame skip 2).
While editing: only when the editor's revision, the canvas size or the message changes.
"""

from __future__ import annotations

import collections
import logging
import secrets
import threading
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from server.play import draw
from server.play.buttons import PlayButtons
from server.play.editing import PointerInput, default_editor_factory
from server.play.frames import (
    FIRST_FRAME_WAIT_S,
    JPEG_QUALITY,
    ack_html,
    canvas_view,
    set_background_jpeg,
    wait_until_sent,
)
from server.play.hooks import Controller, PlayListener, episode_end
from server.play.loop import PlayLoop
from server.play.scheduler import StepPlan
from server.play.steps import DEFAULT_CLOCKWISE, PLAY_KEYS, action_from_keys, stepper_for
from server.play.warmup import PREPARING

__all__ = ["RESULT_TEXT", "START_HINT", "Controller", "PlayListener", "Session", "StepPlan", "episode_end"]

log = logging.getLogger(__name__)

RESULT_TEXT = {"solved": "You won!", "failed": "You lost.", "truncated": "Time is up.", "nan": "The simulation broke.",
               "stopped": "Stopped."}
SNAP_PIXELS = 6  # on screen: how close the pointer must come to a feature to snap to it (server.editor.gestures)
MAX_FIELDS = 32  # text fields taken from one dialog (set_fields)
START_HINT = "Press Space or an arrow key to start"  # on the canvas while a play waits for the player (mode "ready")


class SessionHost(Protocol):
    """What a session needs of its manager (server.play.manager.SessionManager is one; it imports this module, so
    this one names only the part it uses)."""

    editor_factory: Callable | None
    on_session_gui: Callable[[Session], None] | None
    on_play_end: Callable[[Session, str, int, float], None] | None
    scheduler: Any  # server.play.scheduler.PlayScheduler: add(), wake()
    encoder: Any  # concurrent.futures.Executor of the frame encoders
    warmup: Any  # server.play.warmup.WarmUp or None

    def notify(self, event: str, *args) -> None: ...

    def preparing(self) -> str | None: ...


class Session(PlayLoop):
    """One tab. Build with SessionManager; `client` is a viser ClientHandle (or a test double with .scene/.gui)."""

    def __init__(self, client, manager: SessionHost, level=None, size: str = "m"):
        editor_factory = manager.editor_factory or default_editor_factory()
        self.client = client
        self.manager = manager
        self.nonce = secrets.token_urlsafe(16)
        self.lock = threading.RLock()
        self.editor = editor_factory(level, size=size)
        self.mode = "edit"  # "edit" | "ready" (waits for the first key) | "play" | "paused" | "ended" | "replay"
        self.held: set[str] = set()
        self.clockwise = DEFAULT_CLOCKWISE  # per motor binding, the value its keys' clockwise turn drives (play())
        self.closed = False
        self.frames_sent = 0
        self.last_key_seq = -1
        self._play = None  # (stepper, state, params) while not editing
        self._result: str | None = None
        self._steps = 0
        self._step_request = False
        self._key_pending = False
        self._play_id = 0  # counts plays, so a step computed for an earlier play is dropped
        self._play_scene: draw.Scene | None = None  # the play's drawn scene (its static parts are reused per frame)
        self._play_motion = None  # play.Motion of the state in _play, fetched with its step (None: fetch to draw)
        self._pending_push = None  # the Future of this session's frame being encoded and sent, if any
        self._next_tick: float | None = None
        self._message: str | None = None
        self._status: str | None = None  # what the tab waits for (show_status)
        self._waiting_play: tuple | None = None  # (controller, wait) of a play asked for before its step compiled
        self._pushed_key = None  # what the last edit-mode frame showed, to push only on change
        self.pointer_log: collections.deque[str] = collections.deque(maxlen=50)  # recent editor calls (debugging)
        self._view = draw.View(512, 512)
        self.author_token: str | None = None  # the tab's gallery author token (from localStorage, via /keys)
        # The tab's own random key (from sessionStorage, via /keys): the same after a reload or a reconnect through
        # another process, so the tab's last play is found again (server.recordings.recent).
        self.tab_key: str | None = None
        self._gallery_id: str | None = None  # the gallery level this tab opened or saved, if any
        self.controller: Controller | None = None  # set by play(controller=...): the agent playing, or None
        self.replay = None  # a server.recordings.replay.Replay while the tab shows a recording (mode "replay")
        self.ended_player = "human"  # the player of the last play that ended (see finish_step)
        self.query_lock = threading.Lock()  # held while the page's address is opened (SessionManager.open_query)
        self.query_opened = False

        # The level first, then the panel: the page draws this frame before viser builds the panel, which keeps
        # the browser's main thread busy for a second or more (the canvas stayed blank that long, issue 37).
        self._push_frame()
        wait_until_sent(self.client, FIRST_FRAME_WAIT_S)  # else a later frame can replace it, behind the panel
        self._build_gui()
        self._pointer = PointerInput(self)
        self.refresh(force=True)
        manager.notify("session_opened", self)

    @property
    def gallery_id(self) -> str | None:
        """The gallery level this tab opened or saved, if any (a later save is a remix of it)."""
        return self._gallery_id

    @gallery_id.setter
    def gallery_id(self, level_id: str | None) -> None:
        with self.lock:
            changed, self._gallery_id = level_id != self._gallery_id, level_id
            if changed:
                self.manager.notify("level_changed", self)

    # ------------------------------------------------------------------ GUI and pointer wiring

    def _build_gui(self) -> None:
        gui = self.client.gui
        gui.add_html(f'<div id="kinetix-session" data-nonce="{self.nonce}" hidden></div>')
        self._ack = gui.add_html(ack_html(-1))
        self.buttons = PlayButtons(gui, self)
        self.panel = None
        if self.manager.on_session_gui is not None:
            self.manager.on_session_gui(self)
        try:
            from server.editor import Editor
            from server.editor.panel import EditorPanel
        except ImportError:  # without the editor package the session plays levels only
            return
        if not isinstance(self.editor, Editor):  # a stand-in model (play-only, tests) has no panel
            return
        self.panel = EditorPanel(gui, self.editor, on_change=lambda: self.refresh(),
                                 send_download=self._send_download, lock=self.lock)

    def _send_download(self, filename: str, content: bytes) -> None:
        self.client.send_file_download(filename, content, save_immediately=True)

    def world(self, screen_pos) -> tuple[float, float]:
        u, v = screen_pos
        return self._view.to_world(float(u), float(v))

    def edit_call(self, method: str, *args, **kwargs) -> None:
        self.pointer_log.append(method)
        with self.lock:
            if self.mode != "edit" or self.closed:
                return
            try:
                message = getattr(self.editor, method)(*args, **kwargs)
            except Exception:  # an editor bug must not kill the tab; it is logged and shown
                log.exception("editor.%s failed", method)
                message = f"internal error in {method}"
            if isinstance(message, str) and self.editor.overlay() is None:  # a stand-in without an overlay
                self._message = message
            # The editor's own message (a refusal, "no polygon left: ...") is drawn from its overlay and goes when
            # the editor clears it (the next edit, Move to size, Esc); kept here, it outlived its cause (issue 37).
            if self.panel is not None and hasattr(self.panel, "refresh"):
                self.panel.refresh()
            self.refresh()

    # ------------------------------------------------------------------ keys (from the side server's /keys socket)

    def key_event(self, kind: str, code: str, key: str = "", *, ctrl: bool = False, shift: bool = False,
                  alt: bool = False, meta: bool = False, seq: int = -1) -> None:
        """A keydown ("down") or keyup ("up") from keys.js. Play keys change the held set and wake the play loop."""
        with self.lock:
            if self.closed:
                return
            self.last_key_seq = max(self.last_key_seq, seq)
            if self.mode == "replay" and self.replay is not None and kind == "down" and self.replay.on_key(code, shift):
                return  # ←/→ step the replay (server.recordings.replay)
            if kind == "down" and code == "Space" and not (ctrl or alt or meta):
                self.toggle_play()
                return
            if self.mode == "edit":
                if kind == "down" and key:
                    self.edit_call("key", key, ctrl=ctrl, shift=shift, alt=alt, meta=meta)
                self._push_ack(seq)
                return
            if self.mode == "ready" and kind == "down" and code in PLAY_KEYS:
                self._start()  # the first control key starts the play and acts in its first step
            if code in PLAY_KEYS:
                if kind == "down":
                    self.held.add(code)
                else:
                    self.held.discard(code)
                self._key_pending = True
                self.manager.scheduler.wake()
            elif kind == "down" and code == "Escape":
                self.stop()

    def set_fields(self, values) -> None:
        """The values of a dialog's text fields as the page shows them, sent by keys.js before a click on one of
        the dialog's buttons: viser's client can drop a field's update that came just before another one."""
        if not isinstance(values, dict):
            return
        with self.lock:
            handles = getattr(getattr(self.client, "gui", None), "_gui_input_handle_from_uuid", {})
            for uuid, value in list(values.items())[:MAX_FIELDS]:
                handle = handles.get(uuid) if isinstance(uuid, str) else None
                if handle is not None and isinstance(value, str) and isinstance(handle.value, str):
                    handle.value = value  # text fields only; an unchanged value sends nothing

    def release_all_keys(self) -> None:
        with self.lock:
            self.held.clear()
            self.manager.scheduler.wake()

    # ------------------------------------------------------------------ play control

    def open_level(self, data: bytes, filename: str = "") -> None:
        """Replace the edited level by a level document (either format); raises the editor's error on bad input."""
        with self.lock:
            self.stop()
            self.editor.import_bytes(data, filename)
            if self.panel is not None:
                self.panel.refresh()
            self.refresh(force=True)

    def toggle_play(self) -> None:
        """Space and the Play button: play the edited level now; start a play that waits; else stop playing."""
        with self.lock:
            if self.mode == "edit":
                self.play()
            elif self.mode == "ready":
                self._start()
            else:
                self.stop()

    def keys_action(self) -> np.ndarray:
        """The multi-discrete action of the held keys on the level being played."""
        return action_from_keys(self.held, self.clockwise)

    @property
    def player(self) -> str:
        """Who plays now: "human", or the controller's name (e.g. "agent:general")."""
        return self.controller.player if self.controller is not None else "human"

    def play(self, controller: Controller | None = None, wait: bool = False) -> None:
        """Start playing from the edited level (the editor itself is not changed by playing).

        With a controller, it chooses every action (the keyboard drives nothing) until the play stops. With
        `wait`, the play shows its start with START_HINT and steps nothing (mode "ready") until Space or the first
        control key (which then also acts), so a player who opened a level is not beaten before touching a key.
        """
        with self.lock:
            if self.closed:
                return
            if self.mode != "edit":
                self.stop()
            try:
                level_file = self.editor.level_file()
                if self._wait_for_warmup(level_file.size.name, controller, wait):
                    return
                stepper = stepper_for(level_file)
                state, params = stepper.start(level_file)
            except Exception as error:  # e.g. the level does not build; say why instead of playing
                if not isinstance(error, ValueError):  # a LevelError is the user's to fix; anything else is ours
                    log.exception("could not start a play")
                self._message = f"cannot play: {error}"
                self.refresh(force=True)
                return
            from kinetix.bindings import clockwise_values

            self._play = (stepper, state, params)
            self.clockwise = clockwise_values(level_file.level)
            self._steps, self._result, self._message, self._status = 0, None, None, None
            self._step_request = False
            self.controller = controller
            self.mode = "ready" if wait else "play"
            self._play_id += 1
            self._next_tick = None
            self._play_scene = None
            self._play_motion = None
            self.manager.notify("play_started", self, level_file, params)
            self.set_buttons()
            self.manager.scheduler.add(self)  # a waiting play is only looked at (no tick) until it starts
            if wait:
                self.refresh(force=True)

    def _wait_for_warmup(self, size: str, controller: Controller | None, wait: bool) -> bool:
        """True if this size class's play step is still compiling at start-up: the play then starts by itself when it
        is ready (the tab says "preparing the simulation" meanwhile); asking again only updates what to start."""
        warmup = self.manager.warmup
        if warmup is None or warmup.ready(size):
            return False
        first = self._waiting_play is None
        self._waiting_play = (controller, wait)
        if first and not warmup.when_ready(size, self._warmup_ready):
            self._waiting_play = None
            return False
        self._message = f"{PREPARING} (size {size}): the play starts when it is ready"
        self.refresh(force=True)
        return True

    def _warmup_ready(self) -> None:
        """The play step this tab waited for is compiled: start the play it asked for (on the warm-up thread)."""
        with self.lock:
            if self.closed or self._waiting_play is None:
                return
            (controller, wait), self._waiting_play = self._waiting_play, None
            self._message = None
            self.play(controller, wait=wait)

    def _start(self) -> None:
        """A waiting play starts now: its first step comes at once (or with the key that started it)."""
        if self.mode != "ready":
            return
        self.mode = "play"
        self._next_tick = None
        self._key_pending = True
        self.set_buttons()
        self.manager.scheduler.wake()

    def stop(self) -> None:
        """Back to editing; the edited level is shown again as it was before playing."""
        with self.lock:
            if self.mode == "edit":
                if self._waiting_play is not None:  # Esc or Edit before the step compiled: do not start it then
                    self._waiting_play, self._message = None, None
                    self.refresh(force=True)
                return
            if self.mode == "replay":  # leaving a replay (server.recordings.replay): no play to end
                replay, self.replay = self.replay, None
                if replay is not None:
                    replay.stop()
            elif self.mode != "ended":  # stopped by the player before the episode ended
                self._notify_stopped()
            self.mode = "edit"
            self._play = None
            self.controller = None
            self.held.clear()
            self.set_buttons()
            self.manager.scheduler.wake()
            self.refresh(force=True)

    def _notify_stopped(self) -> None:
        """Tell the listeners the running play was cut short (Stop, a new play, the tab going away)."""
        stepper, _, params = self._play
        self.manager.notify("play_ended", self, "stopped", self._steps,
                            self._steps * float(params.sim.dt) * stepper.frame_skip)

    def play_again(self) -> None:
        with self.lock:
            self.stop()
            self.play(wait=True)

    def toggle_pause(self) -> None:
        with self.lock:
            if self.mode == "play":
                self.mode = "paused"
            elif self.mode == "paused":
                self.mode = "play"
            self.set_buttons()
            self.manager.scheduler.wake()

    def single_step(self) -> None:
        with self.lock:
            if self.mode in ("play", "ready"):
                self.mode = "paused"
                self.set_buttons()
            if self.mode == "paused":
                self._step_request = True
                self.manager.scheduler.wake()

    def show_status(self, text: str | None) -> None:
        """Say on the canvas what the tab waits for ("loading agent general ..."), over the level it shows while
        editing (a message of the tab's own, such as a refusal, goes first); None clears it, and so does a play
        that starts."""
        with self.lock:
            if text != self._status:
                self._status = text
                self.refresh()

    def set_buttons(self) -> None:
        """The Play folder's buttons follow the mode (server.play.buttons)."""
        self.buttons.update(self.mode)

    # ------------------------------------------------------------------ frames

    def canvas(self) -> draw.View:
        """The view at the size of the tab's canvas (server.play.frames.canvas_view)."""
        return canvas_view(self.client)

    def hud(self) -> str:
        if self.mode == "edit":
            preparing = self.manager.preparing()
            return f"EDIT  tool: {getattr(self.editor, 'tool', '?')}   " + (preparing or "Space: play")
        stepper, state, params = self._play
        seconds = self._steps * float(params.sim.dt) * stepper.frame_skip
        if self.controller is not None:
            return f"{self.mode.upper()}  {self.player}  step {self._steps}  {seconds:.2f} s  {self.controller.hud()}"
        held = " ".join(sorted(self.held))
        return f"{self.mode.upper()}  step {self._steps}  {seconds:.2f} s  {held}"

    def render(self) -> np.ndarray:
        """The current frame as RGB (height, width, 3) uint8 at the canvas size."""
        self._view = self.canvas()
        if self.mode == "edit":
            if hasattr(type(self.editor), "snap_radius") or "snap_radius" in vars(self.editor):
                self.editor.snap_radius = SNAP_PIXELS / self._view.scale  # the same few pixels at any canvas size
            level = self.editor.level_file().level
            overlay = self.editor.overlay()
            message = getattr(overlay, "message", None) or self._message or self._status
            return draw.draw_frame(draw.scene_of(level), self._view, overlay=overlay, hud=self.hud(), message=message)
        stepper, state, params = self._play
        banner = START_HINT if self.mode == "ready" else ""
        if self.mode == "ended":
            seconds = self._steps * float(params.sim.dt) * stepper.frame_skip
            banner = f"{RESULT_TEXT.get(self._result, self._result)}\n{seconds:.2f} s, {self._steps} steps"
        if self.controller is not None:
            frame = self.controller.draw(self, self._view, banner)
            if frame is not None:
                return frame
        motion = self._play_motion
        pose = None if motion is None else (motion.position, motion.angle)
        self._play_scene = draw.scene_of(state.level, static_from=self._play_scene, pose=pose)
        return draw.draw_frame(self._play_scene, self._view, hud=self.hud(), banner=banner)

    def refresh(self, force: bool = False) -> None:
        """Push an edit-mode frame (or a waiting play's) if anything visible changed (or `force`); play frames come
        from the loop."""
        with self.lock:
            if self.closed or self.mode not in ("edit", "ready"):  # a waiting play is redrawn like an edit
                return
            key = (getattr(self.editor, "revision", None), self.canvas(), self._message, self._status, self.mode,
                   self.manager.preparing())
            if not force and key == self._pushed_key:
                return
            self._pushed_key = key
            self._push_frame()
            self.manager.notify("level_changed", self)

    def _push_frame(self, ack: bool = False, background: bool = False) -> None:
        """Render now and send the frame; with `background`, encode and send it on the manager's encoder threads.

        JPEG encoding releases the interpreter lock, so the play thread draws the next session's frame while this
        one is encoded. A session's frames still go out in order: every push waits for its previous one.
        """
        if self.closed:
            return
        try:
            frame = self.render()
        except Exception:
            if background:  # on the play thread: the scheduler ends this play with the error, logged once there
                raise
            log.exception("render failed")
            return
        pending = self._pending_push
        if pending is not None and not pending.done():
            pending.result()  # the encoder never takes the session lock, so waiting here cannot deadlock
        seq = self.last_key_seq if ack else None
        playing = self.mode != "edit"
        if background:
            self._pending_push = self.manager.encoder.submit(self._send_frame, frame, seq, playing)
        else:
            self._send_frame(frame, seq, playing)

    def _send_frame(self, frame: np.ndarray, ack_seq: int | None, playing: bool) -> None:
        client = self.client
        if client is None or self.closed:
            return
        try:
            data = draw.encode_jpeg(frame, JPEG_QUALITY)
            with client.atomic():
                set_background_jpeg(client, data, frame)
                if ack_seq is not None:
                    self._ack.content = ack_html(ack_seq)
            client.flush()
        except Exception:  # e.g. the tab went away mid-send
            log.debug("frame not sent", exc_info=True)
            return
        self.frames_sent += 1
        if playing:
            self.manager.notify("frame_pushed", self, data, frame)

    def _push_ack(self, seq: int) -> None:
        if seq >= 0:
            self._ack.content = ack_html(seq)

    # ------------------------------------------------------------------ teardown

    def close(self) -> None:
        """Stop the play loop and drop references (the tab is gone)."""
        with self.lock:
            if self.mode in ("ready", "play", "paused") and self._play is not None:  # cut short: listeners finish it
                self._notify_stopped()
            self.closed = True
            if self.replay is not None:
                self.replay.stop()
                self.replay = None
            self.mode = "edit"
            self._play = None
            self.held.clear()
            self.manager.scheduler.wake()  # it drops this session on its next look
        self.manager.notify("session_closed", self)
        self.panel = None
        self.client = None
