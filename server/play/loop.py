"""The part of a session that the play thread runs (server.play.scheduler's Playable): plan each tick, take the
stepped state and push its frame, end a play that failed. Session (server.play.session) inherits it; the session
holds the state it reads (mode, the play, the tick schedule, the held keys) and its lock."""

from __future__ import annotations

import logging
import math
import threading

import numpy as np

from server.play.hooks import episode_end
from server.play.scheduler import StepPlan

log = logging.getLogger("server.play.session")  # the session's log: these lines are about its plays

BATCH_SLACK_S = 0.002  # sessions due within this much of each other step in one batch
MAX_ERROR_TEXT = 160  # characters of an exception shown in the tab when its play fails


class PlayLoop:
    """Mixed into Session; every method takes the session's lock."""

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
                self.set_buttons()
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
