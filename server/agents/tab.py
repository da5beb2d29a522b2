"""The "Agent" folder of every tab: Watch agent, Race the agent, Train on this level (with progress and cancel).

`AgentLink(store=..., agents_dir=..., pool=...).attach(manager)` chains onto the manager's GUI and query hooks
(after the gallery's), so:
- every tab gets an Agent folder: a choice of agent ("general", the newest specialist, and every specialist of
  the level by name, the project's shipped one last: server.agents.project), Watch agent, Race the agent,
  Train on this level, Cancel training, a progress bar, a status line and a learning-curve image redrawn from
  the worker's progress;
- `/?level=<id>&mode=agent` (the gallery card's "Watch agent") opens the level and starts the agent on it.

Specialists and runs belong to someone (issue 26; docs/agents.md, "Training belongs to someone"):
- A run is BOUND to a gallery level when it starts if the tab holds the author token that owns the level and still
  shows it unchanged ("attach when done"). A bound run goes on after its tab closes; when it finishes it is
  attached to the level (gallery table `level_agents`, checkpoint under `<data dir>/agents/<run>/checkpoint`,
  ownership checked again), so every tab that opens the level can watch it.
- Any other run (a new level, an edited one, or someone else's gallery level) belongs to its tab: it is cancelled
  (worker terminated) when the tab closes, and its specialist is offered in that tab only and deleted with it,
  unless the tab saves the level as its own copy meanwhile (then it is attached to that copy).
- Each tab trains on behalf of a client (its author identity, else the tab itself): the pool's per-client limits
  and round-robin queue (server.agents.training) use it.

Plays: Watch agent plays are recorded by the gallery link (kind "agent", the session's player is
"agent:<name>"). A race records both of its plays itself when it is decided (kind "human" and kind "agent"); the
human's side is the session's own play, recorded to MCAP like any other (player "race"), so a race won by the
human keeps its recording as the level's best run when it sets the best time (server.gallery.runs).
"""

from __future__ import annotations

import html
import json
import logging
import secrets
import threading
from pathlib import Path
from urllib.parse import parse_qs

import numpy as np

from server.agents.play import WINNER_TEXT, AgentController, AgentRunner, RaceController
from server.agents.project import ProjectSpecialists
from server.agents.training import TrainingJob, TrainingPool
from server.agents.training_tab import (
    BEST,
    CURVE_SIZE,
    DEFAULT_TRAIN_STEPS,
    GENERAL,
    MAX_TRAIN_STEPS,
    NEWEST,
    LocalSpecialist,
    RunOwner,
    TabTraining,
    without_name,
)
from server.play.hooks import PlayListener

log = logging.getLogger(__name__)



class AgentLink(TabTraining):
    def __init__(self, *, store=None, agents_dir: str | Path, pool: TrainingPool | None = None,
                 train_steps: int = DEFAULT_TRAIN_STEPS, train_options: dict | None = None, recorder=None):
        from server.gallery.agents import LevelAgents
        from server.gallery.runs import BestRuns

        self.store = store
        self.recorder = recorder  # server.recordings.recorder.PlayRecorder: a race's human solve keeps its recording
        self.runs = BestRuns(store) if store is not None and store.recordings_dir is not None else None
        self.agents_dir = Path(agents_dir)
        self.level_agents = LevelAgents(store, self.agents_dir) if store is not None else None
        self.project = ProjectSpecialists()
        self.pool = pool
        self.train_steps = train_steps
        self.train_options = train_options or {}
        self._lock = threading.Lock()

    def attach(self, manager) -> None:
        previous_gui, previous_query = manager.on_session_gui, manager.on_query

        def on_session_gui(session) -> None:
            if previous_gui is not None:
                previous_gui(session)
            self.build_gui(session)

        def on_query(session, query: str) -> None:
            if previous_query is not None:
                previous_query(session, query)
            self.open_from_query(session, query)

        manager.on_session_gui = on_session_gui
        manager.on_query = on_query
        manager.add_listener(_TabCloser(self))

    def tab(self, session) -> TabAgents:
        # Kept on the session itself, not in a dict keyed by it: its GUI callbacks refer to the session, so a
        # WeakKeyDictionary value would keep its key alive for ever.
        with self._lock:
            tab = getattr(session, "agent_tab", None)
            if tab is None:
                tab = session.agent_tab = TabAgents()
            return tab

    # ------------------------------------------------------------------ GUI

    def build_gui(self, session) -> None:
        gui = session.client.gui
        tab = self.tab(session)
        with gui.add_folder("Agent"):
            tab.choice = gui.add_dropdown("Agent", options=(BEST, GENERAL, NEWEST), initial_value=BEST)
            watch = gui.add_button("Watch agent")
            race = gui.add_button("Race the agent")
            tab.steps = gui.add_number("Training steps", initial_value=self.train_steps, min=1000, max=MAX_TRAIN_STEPS,
                                       step=1000)
            train = gui.add_button("Train on this level", disabled=self.pool is None)
            tab.cancel = gui.add_button("Cancel training", disabled=True)
            tab.bar = gui.add_progress_bar(0.0, visible=False)
            tab.status = gui.add_markdown("")
            tab.curve = gui.add_image(np.full((CURVE_SIZE[1], CURVE_SIZE[0], 3), 255, np.uint8), label="Training",
                                      format="png", visible=False)
        watch.on_click(lambda _event: self._guarded(session, self.watch, session))
        race.on_click(lambda _event: self._guarded(session, self.race, session))
        train.on_click(lambda _event: self._guarded(session, self.train, session))
        tab.cancel.on_click(lambda _event: self.cancel_training(session))
        tab.choice.on_update(lambda _event: None)

    def _guarded(self, session, action, *args) -> None:
        """Run a button's action; a refusal (bad agent, level that does not build) is shown, not raised."""
        try:
            action(*args)
        except Exception as error:
            log.info("agent action refused: %s", error)
            session.show_status(None)  # "loading agent ..." on the canvas: nothing comes
            self._say(session, f"**Cannot do that:** {html.escape(str(error))}")
        finally:  # the tab may show another level by now (Open from gallery): offer its specialists
            try:
                self.refresh_choices(session)
            except Exception:
                log.exception("could not refresh the agent choices")

    def _say(self, session, text: str) -> None:
        tab = self.tab(session)
        if tab.status is not None and not session.closed:
            tab.status.content = text

    def refresh_choices(self, session) -> None:
        tab = self.tab(session)
        if tab.choice is None or session.closed:
            return
        labels = [BEST, GENERAL, NEWEST] + [label for label, _ in self.specialists(session)]
        current = tab.choice.value
        tab.choice.options = tuple(dict.fromkeys(labels))
        if current in labels:
            tab.choice.value = current

    # ------------------------------------------------------------------ choosing an agent

    def specialists(self, session) -> list[tuple[str, str]]:
        """(label, checkpoint dir) of the specialists for the tab's level, newest first."""
        self._adopt_saved(session)
        out = [(local.label, str(self.agents_dir / local.run_name / "checkpoint"))
               for local in reversed(self.tab(session).local)]
        level_id = session.gallery_id
        if self.level_agents is not None and level_id is not None:
            try:
                out += [(f"{row['name']} (#{row['id']})", str(row["path"])) for row in self.level_agents.list(level_id)]
            except Exception:
                log.exception("could not list the specialists of %s", level_id)
        try:  # last: one trained for this level by someone here is preferred
            out += self.project.matching(json.loads(session.editor.export("ours")))
        except Exception:
            log.exception("could not match the tab's level with the project's specialists")
        return out

    def _adopt_saved(self, session) -> None:
        """The tab's own specialists whose level has since been saved to the gallery (unchanged) by this tab's
        author are attached to it and kept for good."""
        tab = self.tab(session)
        if not tab.local or self.level_agents is None or session.gallery_id is None:
            return
        if not self.level_agents.owns(session.gallery_id, session.author_token):
            return  # someone else's level: the tab's specialists stay with the tab
        try:
            stored = without_name(self.store.get_level(session.gallery_id)["level"])
        except Exception:
            return
        for local in list(tab.local):
            try:
                trained_on = json.loads((self.agents_dir / local.run_name / "level.json").read_text())
                if without_name(trained_on) != stored:
                    continue
                self.level_agents.attach(session.gallery_id, local.run_name, token=session.author_token,
                                         steps=local.steps,
                                         solve_rate=local.solve_rate, mean_return=local.mean_return,
                                         name=local.label.replace("this tab's ", ""))
            except Exception as error:
                log.warning("tab specialist %s not attached: %s", local.run_name, error)
                continue
            local.finalizer.detach()  # the gallery owns it now: keep the files when the tab closes
            tab.local.remove(local)

    def resolve(self, session, choice: str | None) -> tuple[str, str]:
        """(label, load_policy spec) for a dropdown label, "general", "noop", "random", "newest specialist" or
        "best" (the newest specialist if the level has one, else general)."""
        choice = choice or (self.tab(session).choice.value if self.tab(session).choice is not None else BEST)
        if choice in (GENERAL, "noop", "random"):
            return choice, choice
        specialists = self.specialists(session)
        if choice in (BEST, "best"):
            return specialists[0] if specialists else (GENERAL, GENERAL)
        if choice == NEWEST:
            if not specialists:
                raise ValueError("this level has no specialist yet: train one (Train on this level)")
            return specialists[0]
        for label, path in specialists:
            if label == choice:
                return label, path
        raise ValueError(f"no agent {choice!r} for this level")

    def runner(self, session, choice: str | None = None, policy=None) -> AgentRunner:
        from server.play.steps import stepper_for

        label, spec = self.resolve(session, choice) if policy is None else (policy.name, policy.name)
        level_file = session.editor.level_file()
        self._say(session, f"Preparing **{html.escape(label)}** (the first time for a size class compiles it)...")
        # On the canvas too, over the level it keeps showing: reading and compiling an agent can take a minute. The
        # play it starts clears it (a refusal: _guarded).
        session.show_status(f"loading agent {label}: the first time for a size class compiles it")
        runner = AgentRunner(spec, level_file.size, label=label.split(" (#")[0], policy=policy,
                             seed=secrets.randbits(31))
        runner.warm(stepper_for(level_file).start(level_file)[0])  # here, not on the play thread
        return runner

    # ------------------------------------------------------------------ watch and race

    def watch(self, session, choice: str | None = None, policy=None) -> AgentController:
        """Start the agent playing the tab's level (the keyboard drives nothing until the play stops)."""
        controller = AgentController(self.runner(session, choice, policy))
        session.play(controller=controller)
        self._say(session, f"Watching **{html.escape(controller.runner.label)}**. Space or Esc: back to editing.")
        return controller

    def race(self, session, choice: str | None = None, policy=None) -> RaceController:
        """Start a race: the human plays the left half with the keys, the agent the right half."""
        from server.play.steps import stepper_for

        runner = self.runner(session, choice, policy)
        level_file = session.editor.level_file()
        stepper = stepper_for(level_file)
        state, params = stepper.start(level_file)
        race = RaceController(session, runner, stepper, state, params, on_finish=self._race_finished)
        race.gallery_id = session.gallery_id
        session.play(controller=race, wait=True)  # both sides start with the human's first key
        self._say(session, f"Racing **{html.escape(runner.label)}**: you play the left half. First to solve wins. "
                           "Press Space or an arrow key to start.")
        return race

    def _race_finished(self, race: RaceController) -> None:
        try:
            self._record_race(race)
        finally:
            race.recorded.set()

    def _record_race(self, race: RaceController) -> None:
        session = race.session
        self._say(session, f"**{WINNER_TEXT[race.winner]}** You: {race.human.result or 'still playing'}, "
                           f"{race.human.seconds:.2f} s; agent: {race.agent.result or 'still playing'}, "
                           f"{race.agent.seconds:.2f} s.")
        if self.store is None or race.gallery_id is None:
            return
        # Both plays are recorded; a side still playing when the other solved lost the race: recorded unsolved,
        # with the steps it had played.
        for side, kind in ((race.human, "human"), (race.agent, "agent")):
            best = self._race_best_run(race) if kind == "human" else None
            try:
                self.store.record_play(race.gallery_id, kind, solved=side.solved, steps=int(side.steps),
                                       seconds=float(side.seconds), recording_path=best,
                                       author=race.session.author_token if kind == "human" else None)
            except Exception as error:  # a lost statistic is not worth a crash (e.g. the level was deleted)
                log.warning("race play not recorded for %s: %s", race.gallery_id, error)
                if best is not None:
                    self.runs.discard(best)
                continue
            if best is not None:
                self.runs.prune(race.gallery_id)  # the previous best run's file goes

    def _race_best_run(self, race: RaceController) -> str | None:
        """The best-run file of the human's side if it solved and beat the kept best run (else None), so the best
        time a race sets comes with its recording."""
        if self.runs is None or not race.human.solved:
            return None
        session = race.session
        with session.lock:  # the play thread decided the race holding it; past it, the recorder has the play ended
            pass
        return self.runs.candidate(self.recorder, session, "solved", int(race.human.steps),
                                   float(race.human.seconds), player=RaceController.player)

    # ------------------------------------------------------------------ query (?level=<id>&mode=agent)

    def open_from_query(self, session, query: str) -> None:
        params = parse_qs(query.lstrip("?"))
        if (params.get("mode") or [""])[0] != "agent":
            return
        if params.get("level") and session.gallery_id is None:  # the gallery could not open it (and said so)
            return
        self.refresh_choices(session)
        self._guarded(session, self.watch, session, (params.get("agent") or [BEST])[0])

    # ------------------------------------------------------------------ training

    def client_of(self, session) -> str:
        """Who a tab trains for (per-client limits, round-robin queue): its gallery author identity when it holds
        a token the gallery knows (shared by the browser's tabs), else the tab itself."""
        token = session.author_token
        if token and self.store is not None:
            try:
                return "author:" + self.store.author_of(token)
            except Exception:
                pass  # unknown token: the tab counts on its own
        return "tab:" + session.nonce

class _TabCloser(PlayListener):
    """Tells the AgentLink when a tab goes, at once (not at its run's next progress report)."""

    def __init__(self, link: AgentLink):
        self.link = link

    def session_closed(self, session) -> None:
        self.link.tab_closed(session)


class TabAgents:
    """One tab's agent state: its GUI handles, its training job and the specialists that live with it."""

    def __init__(self) -> None:
        self.choice = self.steps = self.cancel = self.bar = self.status = self.curve = None
        self.job: TrainingJob | None = None
        self.owner: RunOwner | None = None  # whose `job` is (bound to a level, or the tab's)
        self.local: list[LocalSpecialist] = []  # trained on a level not in the gallery (oldest first)
