"""One session per browser tab: its editor, play state and lock; and the manager that owns them.

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
import concurrent.futures
import logging
import math
import secrets
import threading
from collections.abc import Callable

import numpy as np

from server.play import draw
from server.play.scheduler import PlayScheduler, StepPlan
from server.play.steps import DEFAULT_CLOCKWISE, PLAY_KEYS, action_from_keys, stepper_for
from server.play.warmup import PREPARING

log = logging.getLogger(__name__)

BATCH_SLACK_S = 0.002  # sessions due within this much of each other step in one batch
MAX_ERROR_TEXT = 160  # characters of an exception shown in the tab when its play fails
MAX_PIXELS = 1280 * 800  # larger canvases are rendered smaller at the same aspect ratio (the browser scales up)
JPEG_QUALITY = 85
RESULT_TEXT = {"solved": "You won!", "failed": "You lost.", "truncated": "Time is up.", "nan": "The simulation broke.",
               "stopped": "Stopped."}
START_HINT = "Press Space or an arrow key to start"  # on the canvas while a play waits for the player (mode "ready")


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

    def play_started(self, session: Session, level_file, params) -> None:
        """A play began from `level_file` (the edited level, or the opened one) with these env params."""

    def play_stepped(self, session: Session, action: np.ndarray, state, result) -> None:
        """One agent step was taken: the action used, the env state after it and its play.StepResult."""

    def frame_pushed(self, session: Session, jpeg: bytes, frame: np.ndarray) -> None:
        """A play frame (not an edit frame) went to the tab: its JPEG bytes and RGB pixels.

        Runs on an encoder thread without the session's lock (frames are encoded in parallel with play)."""

    def play_ended(self, session: Session, result: str, steps: int, seconds: float) -> None:
        """The episode ended ("solved" | "failed" | "truncated" | "nan"), or was stopped ("stopped")."""

    def level_changed(self, session: Session) -> None:
        """The edited level or its undo history may have changed (after an edit-mode frame, and when the tab's
        gallery level changes); runs with the session's lock held. server.drafts.tab keeps drafts with it."""

    def session_opened(self, session: Session) -> None:
        """A tab's session was built (its GUI exists): add per-tab GUI here (e.g. server.recordings.replay's panel)."""

    def session_closed(self, session: Session) -> None:
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

    def draw(self, session: Session, view: draw.View, banner: str) -> np.ndarray | None:
        """A play frame of its own (e.g. an overlay, a race's two halves), or None for the usual one."""
        return None


def default_editor_factory() -> Callable:
    """server.editor.Editor (CONTRACT section 3); without that package, a play-only stand-in so serving still works."""
    try:
        from server.editor import Editor
    except ImportError:
        log.warning("server.editor is not installed: levels can be played but not edited")
        return PlayOnlyEditor
    return Editor


class PlayOnlyEditor:
    """The part of the Editor interface a session needs to show and play a level, with every edit refused."""

    tool = "none"
    selection: list = []

    def __init__(self, level=None, size: str = "m"):
        from kinetix.formats import describe
        from kinetix.level import LevelFile, empty_level, size_class

        if level is None:
            level = LevelFile(empty_level(size_class(size)))
        self._level_file = level if isinstance(level, LevelFile) else None
        if self._level_file is None:
            from kinetix.formats import build

            self._level_file = build(level, size_class(size))
        self.spec = describe(self._level_file.level, self._level_file.params)
        self.size = self._level_file.size
        self.revision = 0

    def level_file(self):
        return self._level_file

    def overlay(self):
        return None

    def key(self, key: str, **mods) -> bool:
        return False

    def __getattr__(self, name: str):  # pointer_down, click, box_select, ...: no editing without the editor
        if name.startswith("_"):
            raise AttributeError(name)
        return lambda *args, **kwargs: "editing needs the server.editor package"


def _ack_html(seq: int) -> str:
    """The hidden element that acknowledges key `seq` in the batch of the frame it produced (static/frames.js and
    the benchmark read this exact form)."""
    return f'<div id="kinetix-ack" data-seq="{seq}" hidden></div>'


def _set_background_jpeg(client, data: bytes, frame: np.ndarray) -> None:
    """Queue an already encoded JPEG as the scene background.

    Pillow encodes a frame about twice as fast as viser's imageio fallback (no OpenCV here), which matters with 8
    sessions at 30 fps. viser 1.1.1 (pinned) has no public call for encoded bytes, so this queues the same message
    set_background_image would, and falls back to the public call if viser's internals ever differ.
    """
    try:
        from viser._messages import BackgroundImageMessage

        queue = client.scene._websock_interface.queue_message
    except (ImportError, AttributeError):
        client.scene.set_background_image(frame, format="jpeg", jpeg_quality=JPEG_QUALITY)
        return
    queue(BackgroundImageMessage(format="jpeg", rgb_data=data, depth_data=None))


class Session:
    """One tab. Build with SessionManager; `client` is a viser ClientHandle (or a test double with .scene/.gui)."""

    def __init__(self, client, manager: SessionManager, level=None, size: str = "m"):
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
        self._waiting_play: tuple | None = None  # (controller, wait) of a play asked for before its step compiled
        self._pushed_key = None  # what the last edit-mode frame showed, to push only on change
        self.pointer_log: collections.deque[str] = collections.deque(maxlen=50)  # recent editor calls (debugging)
        self._view = draw.View(512, 512)
        self.author_token: str | None = None  # the tab's gallery author token (from localStorage, via /keys)
        self._gallery_id: str | None = None  # the gallery level this tab opened or saved, if any
        self.controller: Controller | None = None  # set by play(controller=...): the agent playing, or None
        self.replay = None  # a server.recordings.replay.Replay while the tab shows a recording (mode "replay")
        self.ended_player = "human"  # the player of the last play that ended (see finish_step)
        self._build_gui()
        self._wire_pointer()
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
        self._ack = gui.add_html(_ack_html(-1))
        with gui.add_folder("Play"):
            self._play_button = gui.add_button("Play (Space)", icon=None)
            self._pause_button = gui.add_button("Pause", disabled=True)
            self._step_button = gui.add_button("Step", disabled=True)
            self._again_button = gui.add_button("Play again", visible=False)
            self._edit_button = gui.add_button("Edit", visible=False)
        self._play_button.on_click(lambda _: self.toggle_play())
        self._pause_button.on_click(lambda _: self.toggle_pause())
        self._step_button.on_click(lambda _: self.single_step())
        self._again_button.on_click(lambda _: self.play_again())
        self._edit_button.on_click(lambda _: self.stop())
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

    def _wire_pointer(self) -> None:
        # viser runs plain callbacks on a thread pool fire-and-forget, so a drag's start and update could run out
        # of order; async callbacks run in arrival order on viser's event loop. They only do quick editor calls
        # and an edit-mode render (a few ms).
        async def on_click(event) -> None:
            self._on_click(event)

        async def on_rect_select(event) -> None:
            self._on_rect_select(event)

        async def on_drag(event) -> None:
            self._on_drag(event)

        scene = self.client.scene
        scene.on_click()(on_click)
        scene.on_rect_select(modifier="shift")(on_rect_select)
        # An invisible sphere around the camera catches drags anywhere on the canvas (study section 2).
        self._catcher = scene.add_icosphere("/kinetix/catcher", radius=200.0, color=(255, 255, 255), opacity=0.0,
                                            side="double")
        self._catcher.on_drag("left")(on_drag)
        self.client.camera.on_update(lambda _: self.refresh())

    def world(self, screen_pos) -> tuple[float, float]:
        u, v = screen_pos
        return self._view.to_world(float(u), float(v))

    def _edit_call(self, method: str, *args, **kwargs) -> None:
        self.pointer_log.append(method)
        with self.lock:
            if self.mode != "edit" or self.closed:
                return
            try:
                message = getattr(self.editor, method)(*args, **kwargs)
            except Exception:  # an editor bug must not kill the tab; it is logged and shown
                log.exception("editor.%s failed", method)
                message = f"internal error in {method}"
            if isinstance(message, str):
                self._message = message
            if self.panel is not None and hasattr(self.panel, "refresh"):
                self.panel.refresh()
            self.refresh()

    def _on_click(self, event) -> None:
        x, y = self.world(event.screen_pos[0] if isinstance(event.screen_pos[0], list | tuple) else event.screen_pos)
        self._edit_call("click", x, y)

    def _on_rect_select(self, event) -> None:
        x0, y0 = self.world(event.screen_min)
        x1, y1 = self.world(event.screen_max)
        self._edit_call("box_select", min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1), add=False)

    def _on_drag(self, event) -> None:
        mods = {"shift": event.modifier in ("shift", "shift+ctrl"), "ctrl": event.modifier in ("ctrl", "cmd/ctrl")}
        if event.phase == "start":
            self._edit_call("pointer_down", *self.world(event.start_screen_pos), **mods)
            self._edit_call("pointer_move", *self.world(event.end_screen_pos), **mods)
        elif event.phase == "update":
            self._edit_call("pointer_move", *self.world(event.end_screen_pos), **mods)
        else:
            self._edit_call("pointer_up", *self.world(event.end_screen_pos), **mods)

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
                    self._edit_call("key", key, ctrl=ctrl, shift=shift, alt=alt, meta=meta)
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
            self._steps, self._result, self._message = 0, None, None
            self._step_request = False
            self.controller = controller
            self.mode = "ready" if wait else "play"
            self._play_id += 1
            self._next_tick = None
            self._play_scene = None
            self._play_motion = None
            self.manager.notify("play_started", self, level_file, params)
            self._set_buttons()
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
        self._set_buttons()
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
            self._set_buttons()
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
            self._set_buttons()
            self.manager.scheduler.wake()

    def single_step(self) -> None:
        with self.lock:
            if self.mode in ("play", "ready"):
                self.mode = "paused"
                self._set_buttons()
            if self.mode == "paused":
                self._step_request = True
                self.manager.scheduler.wake()

    def _set_buttons(self) -> None:
        editing = self.mode == "edit"
        self._play_button.label = ("Play (Space)" if editing else "Start (Space)" if self.mode == "ready"
                                   else "Stop (Space)")
        self._pause_button.disabled = self.mode not in ("play", "paused")
        self._pause_button.label = "Resume" if self.mode == "paused" else "Pause"
        self._step_button.disabled = self.mode not in ("play", "paused", "ready")
        self._again_button.visible = self.mode == "ended"
        self._edit_button.visible = self.mode in ("ended", "ready")

    # ------------------------------------------------------------------ the play loop (run by server.play.scheduler)

    def plan(self, now: float) -> StepPlan:
        """Decide this tick: step (with the action to take), push a key-acknowledging frame, wait, or drop."""
        with self.lock:
            if self.closed or self.mode == "edit" or self._play is None:
                return StepPlan("drop")
            stepper, state, params = self._play
            tick = float(params.sim.dt) * stepper.frame_skip
            if self._next_tick is None:  # the first step comes at the next point of the shared tick grid
                self._next_tick = math.ceil(now / tick) * tick
            key_now, self._key_pending = self._key_pending, False
            step_request, self._step_request = self._step_request, False
            due = now >= self._next_tick - BATCH_SLACK_S
            if not ((self.mode == "play" and (due or key_now)) or (self.mode == "paused" and step_request)):
                if key_now:
                    return StepPlan("frame", next_tick=self._playing_tick())
                return StepPlan("wait", next_tick=self._playing_tick())
            if self.mode == "play":
                # A fixed schedule (not "now + tick") so the work of a frame does not lower the frame rate; a
                # key-driven early step takes the coming slot; after a stall the schedule restarts on the grid.
                late = now - self._next_tick >= tick
                self._next_tick = math.ceil(now / tick) * tick + tick if late else self._next_tick + tick
            action = self._choose_action(state, params)
            if action is None:
                return StepPlan("drop")
            return StepPlan("step", next_tick=self._playing_tick(), stepper=stepper, state=state, params=params,
                            action=action, play_id=self._play_id, ack=key_now)

    def _playing_tick(self) -> float | None:
        return self._next_tick if self.mode == "play" else None

    def _choose_action(self, state, params) -> np.ndarray | None:
        if self.controller is None:
            return self.keys_action()
        try:
            return np.asarray(self.controller.act(state, params), np.int32)
        except Exception:  # a broken controller stops its play instead of breaking the loop
            log.exception("controller %s failed", self.controller.player)
            self._message = f"{self.controller.player} failed; see the server log"
            self.stop()
            return None

    def finish_step(self, plan: StepPlan, state, result) -> None:
        """Take the stepped state (unless the play was stopped or restarted meanwhile) and push its frame."""
        with self.lock:
            if self.closed or self.mode == "edit" or plan.play_id != self._play_id:
                return
            stepper, _, params = self._play
            self._play = (stepper, state, params)
            self._play_motion = result.motion
            self._steps = result.timestep
            self.manager.notify("play_stepped", self, plan.action, state, result)
            end = episode_end(result) if self.controller is None else self.controller.episode_end(state, result)
            if end is not None:
                self._result = end
                self.mode = "ended"
                self.held.clear()
                self._set_buttons()
                seconds = result.timestep * float(params.sim.dt) * stepper.frame_skip
                self.ended_player = self.player  # who played it, for on_play_end (a new play may start meanwhile)
                self.manager.notify("play_ended", self, self._result, result.timestep, seconds)
                if self.manager.on_play_end is not None:  # e.g. the gallery's play statistics; off the play thread
                    threading.Thread(target=self.manager.on_play_end,
                                     args=(self, self._result, result.timestep, seconds), daemon=True).start()
            self._push_frame(ack=plan.ack, background=True)

    def play_failed(self, error: BaseException, play_id: int | None = None) -> None:
        """The play scheduler could not step or draw this play: end it and say why in the tab (the status line of
        the edit view and a notification). Other tabs are not affected. `play_id`: the play that failed (a newer
        play started meanwhile is left alone); None for the current one."""
        with self.lock:
            if self.closed or self.mode in ("edit", "replay") or (play_id is not None and play_id != self._play_id):
                return
            detail = f"{type(error).__name__}: {error}"
            detail = detail if len(detail) <= MAX_ERROR_TEXT else detail[:MAX_ERROR_TEXT - 3] + "..."
            self._message = f"Play stopped: the simulation failed ({detail}). See the server log."
            self.stop()  # back to editing: the message shows in the edit view's status line
            client = self.client
        try:
            client.add_notification("Play stopped", self._message, color="red", with_close_button=True)
        except Exception:  # a tab that went away, or a test double without notifications
            log.debug("could not notify the tab of its failed play", exc_info=True)

    def push_ack_frame(self) -> None:
        with self.lock:
            if not self.closed and self.mode != "edit":
                self._push_frame(ack=True, background=True)

    # ------------------------------------------------------------------ frames

    def _canvas(self) -> draw.View:
        cam = self.client.camera
        try:
            w, h = int(cam.image_width), int(cam.image_height)
        except Exception:  # the camera is not known yet
            w, h = 512, 512
        w, h = max(w, 64), max(h, 64)
        if w * h > MAX_PIXELS:
            f = (MAX_PIXELS / (w * h)) ** 0.5
            w, h = int(w * f), int(h * f)
        return draw.View(w, h)

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
        self._view = self._canvas()
        if self.mode == "edit":
            level = self.editor.level_file().level
            overlay = self.editor.overlay()
            message = getattr(overlay, "message", None) or self._message
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
            key = (getattr(self.editor, "revision", None), self._canvas(), self._message, self.mode,
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
                _set_background_jpeg(client, data, frame)
                if ack_seq is not None:
                    self._ack.content = _ack_html(ack_seq)
            client.flush()
        except Exception:  # e.g. the tab went away mid-send
            log.debug("frame not sent", exc_info=True)
            return
        self.frames_sent += 1
        if playing:
            self.manager.notify("frame_pushed", self, data, frame)

    def _push_ack(self, seq: int) -> None:
        if seq >= 0:
            self._ack.content = _ack_html(seq)

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
