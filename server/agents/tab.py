"""The "Agent" folder of every tab: Watch agent, Race the agent, Train on this level (with progress and cancel).

`AgentLink(store=..., agents_dir=..., pool=...).attach(manager)` chains onto the manager's GUI and query hooks
(after the gallery's), so:
- every tab gets an Agent folder: a choice of agent ("general", the newest specialist, and every specialist of
  the level by name), Watch agent, Race the agent, Train on this level, Cancel training, a progress bar, a
  status line and a learning-curve image redrawn from the worker's progress;
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

import dataclasses
import html
import json
import logging
import secrets
import shutil
import threading
import time
import weakref
from pathlib import Path
from urllib.parse import parse_qs

import numpy as np
from PIL import Image, ImageDraw

from server.agents.play import WINNER_TEXT, AgentController, AgentRunner, RaceController
from server.agents.training import TrainingJob, TrainingPool
from server.play.hooks import PlayListener

log = logging.getLogger(__name__)

GENERAL = "general"
NEWEST = "newest specialist"
BEST = "best: newest specialist, else general"
DEFAULT_TRAIN_STEPS = 100_000
MAX_TRAIN_STEPS = 10_000_000  # a tab cannot start a run of days by a typo
CURVE_SIZE = (300, 130)


class AgentLink:
    def __init__(self, *, store=None, agents_dir: str | Path, pool: TrainingPool | None = None,
                 train_steps: int = DEFAULT_TRAIN_STEPS, train_options: dict | None = None, recorder=None):
        from server.gallery.agents import LevelAgents
        from server.gallery.runs import BestRuns

        self.store = store
        self.recorder = recorder  # server.recordings.recorder.PlayRecorder: a race's human solve keeps its recording
        self.runs = BestRuns(store) if store is not None and store.recordings_dir is not None else None
        self.agents_dir = Path(agents_dir)
        self.level_agents = LevelAgents(store, self.agents_dir) if store is not None else None
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
            stored = _without_name(self.store.get_level(session.gallery_id)["level"])
        except Exception:
            return
        for local in list(tab.local):
            try:
                trained_on = json.loads((self.agents_dir / local.run_name / "level.json").read_text())
                if _without_name(trained_on) != stored:
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
                                       seconds=float(side.seconds), recording_path=best)
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

    def train(self, session, steps: int | None = None, options: dict | None = None) -> TrainingJob:
        """Train a specialist on the tab's level in a worker process (queued beyond the pool's cap)."""
        if self.pool is None:
            raise ValueError("training is off on this server")
        tab = self.tab(session)
        if tab.job is not None and not tab.job.finished:
            raise ValueError("this tab is already training; cancel it first")
        document = json.loads(session.editor.export("ours"))
        steps = int(steps if steps is not None else (tab.steps.value if tab.steps is not None else self.train_steps))
        if not 1 <= steps <= MAX_TRAIN_STEPS:
            raise ValueError(f"training steps must be between 1 and {MAX_TRAIN_STEPS:,}, got {steps:,}")
        owner = RunOwner()
        owner.level_id = self._owned_level(session, document)
        owner.token = session.author_token if owner.level_id is not None else None
        # Gallery ids may start with '-' or '_'; a run name always starts with a letter (a plain directory name).
        run_name = f"run-{owner.level_id or 'tab'}-{time.strftime('%Y%m%d-%H%M%S')}-{secrets.token_hex(3)}"
        run_dir = self.agents_dir / run_name
        run_dir.mkdir(parents=True, exist_ok=False)
        (run_dir / "level.json").write_text(json.dumps(document))
        session_ref = weakref.ref(session)
        try:
            job = self.pool.submit(run_dir / "level.json", run_dir, steps=steps, client=self.client_of(session),
                                   options={**self.train_options, **(options or {})},
                                   on_update=lambda job: self._show_progress(session_ref(), job, owner),
                                   on_done=lambda job: self._training_done(session_ref(), job, owner, run_name))
        except Exception:  # refused (a limit, the queue cap): nothing of it stays
            shutil.rmtree(run_dir, ignore_errors=True)
            raise
        tab.job, tab.owner = job, owner
        if tab.cancel is not None:
            tab.cancel.disabled = False
        if session.closed:  # the tab went while the run was being submitted
            self.tab_closed(session)
        else:
            self._show_progress(session, job, owner)
        return job

    def _owned_level(self, session, document: dict) -> str | None:
        """The tab's gallery level if the tab's author token owns it and the tab shows it unchanged, else None:
        only then is a specialist trained on `document` attached to it."""
        level_id = session.gallery_id
        if self.level_agents is None or level_id is None or not session.author_token:
            return None
        if not self.level_agents.owns(level_id, session.author_token):
            return None
        return level_id if self._unchanged(level_id, document) else None

    def _unchanged(self, level_id: str, document: dict) -> bool:
        try:
            stored = self.store.get_level(level_id)["level"]
        except Exception:
            return False
        return _without_name(stored) == _without_name(document)

    def cancel_training(self, session) -> None:
        tab = self.tab(session)
        if tab.job is not None and not tab.job.finished and self.pool is not None:
            self.pool.cancel(tab.job)

    def tab_closed(self, session) -> None:
        """The tab went: its unbound run is cancelled (worker terminated), its own specialists deleted, unless
        the tab owns its gallery level by now (saved its own copy), then they are attached there."""
        tab = getattr(session, "agent_tab", None)
        if tab is None:
            return
        job, owner = tab.job, tab.owner
        if job is not None and not job.finished and owner is not None and owner.level_id is None:
            try:
                document = json.loads((job.out_dir / "level.json").read_text())
                owner.level_id = self._owned_level(session, document)
            except Exception:
                owner.level_id = None
            if owner.level_id is not None:  # saved as the tab author's own level since: attach when done
                owner.token = session.author_token
            elif self.pool is not None:
                self.pool.cancel(job)
        try:
            self._adopt_saved(session)
        except Exception:
            log.exception("could not attach the closed tab's specialists")
        for local in tab.local:
            local.finalizer()  # delete the run's files now, not when the session is collected
        tab.local.clear()

    def _show_progress(self, session, job: TrainingJob, owner: RunOwner | None = None) -> None:
        if session is None or session.closed:  # tab_closed decided the run's fate (it may bind a saved copy's)
            if session is None and (owner is None or owner.level_id is None) and self.pool is not None:
                self.pool.cancel(job)  # a safety net: a collected tab was closed first
            return
        tab = self.tab(session)
        if tab.job is not job:
            return
        if tab.bar is not None:
            tab.bar.visible = True
            tab.bar.value = round(100 * job.fraction, 1)
        where = (" It goes on if you close this tab and is attached to this level when done."
                 if owner is not None and owner.level_id is not None else " It stops if you close this tab.")
        if job.state == "queued" and self.pool is not None:
            position = self.pool.position(job)
            pool = self.pool
            why = (f"it waits for your other run (at most {pool.per_client} at a time per person)"
                   if pool.waits_for_own_run(job) else
                   f"at most {pool.max_running} run{'s' if pool.max_running > 1 else ''} at a time; "
                   "the queue takes turns between people")
            self._say(session, f"Training queued: position **{position}** ({why}).{where}")
        elif job.state == "running":
            if job.progress:
                last = job.progress[-1]
                self._say(session, f"Training: {int(last['env_steps']):,} / {int(last['total_steps']):,} steps, "
                                   f"return {last['mean_return']:.2f}, solved {100 * last['solve_rate']:.0f}%, "
                                   f"{last['steps_per_second']:.0f} steps/s.{where}")
                if tab.curve is not None:
                    tab.curve.image = curve_image(job.progress)
                    tab.curve.visible = True
            else:
                self._say(session, f"Training: starting the worker and compiling (about a minute)...{where}")

    def _training_done(self, session, job: TrainingJob, owner: RunOwner, run_name: str) -> None:
        run_dir = self.agents_dir / run_name
        if job.state != "done":
            shutil.rmtree(run_dir, ignore_errors=True)
        attached = None
        if job.state == "done":
            result = job.result or {}
            if owner.level_id is not None and self.level_agents is not None:
                try:
                    trained_on = json.loads((run_dir / "level.json").read_text())
                    if not self._unchanged(owner.level_id, trained_on):
                        raise ValueError("the level was changed during the run")
                    agent_id = self.level_agents.attach(
                        owner.level_id, run_name, token=owner.token, steps=int(result.get("steps") or 0),
                        solve_rate=result.get("solve_rate"), mean_return=result.get("mean_return"),
                        name=f"specialist {time.strftime('%m-%d %H:%M')}")
                    attached = f"attached to gallery level {owner.level_id} (#{agent_id})"
                except Exception as error:
                    log.warning("specialist not attached to %s: %s", owner.level_id, error)
            if attached is None:
                if session is None or session.closed:  # the tab is gone and the run belongs to no gallery level
                    shutil.rmtree(run_dir, ignore_errors=True)
                    return
                self.tab(session).local.append(LocalSpecialist(
                    f"this tab's specialist {time.strftime('%H:%M:%S')}", run_name, int(result.get("steps") or 0),
                    result.get("solve_rate"), result.get("mean_return"),
                    weakref.finalize(session, shutil.rmtree, str(run_dir), True)))  # lives as long as the tab
                attached = ("kept with this tab (only the level's author can attach an agent to a gallery level; "
                            "save the level as your own to keep it)")
        if session is None or session.closed:
            return
        tab = self.tab(session)
        if tab.cancel is not None:
            tab.cancel.disabled = True
        if tab.bar is not None:
            tab.bar.value = 100.0 if job.state == "done" else 0.0
        if job.state == "done":
            self.refresh_choices(session)
            if tab.choice is not None:
                tab.choice.value = NEWEST
            solve = (job.result or {}).get("solve_rate")
            solved = f", last solve rate {100 * solve:.0f}%" if solve is not None else ""
            self._say(session, f"**Training done**{solved}: {attached}. Watch agent now uses it.")
        elif job.state == "cancelled":
            self._say(session, "Training cancelled.")
        else:
            self._say(session, f"**Training failed:** {html.escape(job.error or 'unknown error')}")


class _TabCloser(PlayListener):
    """Tells the AgentLink when a tab goes, at once (not at its run's next progress report)."""

    def __init__(self, link: AgentLink):
        self.link = link

    def session_closed(self, session) -> None:
        self.link.tab_closed(session)


@dataclasses.dataclass(eq=False)
class RunOwner:
    """Whose a tab's training run is: the gallery level it is bound to (attached when done; it outlives the tab)
    with the author token that owns that level, or no level (it belongs to the tab and ends with it)."""

    level_id: str | None = None
    token: str | None = None


class TabAgents:
    """One tab's agent state: its GUI handles, its training job and the specialists that live with it."""

    def __init__(self) -> None:
        self.choice = self.steps = self.cancel = self.bar = self.status = self.curve = None
        self.job: TrainingJob | None = None
        self.owner: RunOwner | None = None  # whose `job` is (bound to a level, or the tab's)
        self.local: list[LocalSpecialist] = []  # trained on a level not in the gallery (oldest first)


@dataclasses.dataclass(eq=False)
class LocalSpecialist:
    """A specialist that lives with its tab: its run directory is deleted when the tab goes (`finalizer`),
    unless the level is saved to the gallery meanwhile and it is attached there."""

    label: str
    run_name: str
    steps: int
    solve_rate: float | None
    mean_return: float | None
    finalizer: weakref.finalize


def _without_name(document: dict) -> dict:
    """A level document without its name (the gallery sets the name on save), for comparing levels."""
    return {key: value for key, value in document.items() if key != "name"}


def curve_image(progress: list[dict], size: tuple[int, int] = CURVE_SIZE) -> np.ndarray:
    """A small learning-curve image: mean return (blue, own scale) and solve rate (green, 0..1) over env steps."""
    width, height = size
    image = Image.new("RGB", size, (255, 255, 255))
    pen = ImageDraw.Draw(image)
    left, right, top, bottom = 6, width - 6, 16, height - 6
    pen.rectangle([left, top, right, bottom], outline=(190, 190, 190))
    pen.text((left, 2), "return", fill=(30, 80, 220))
    pen.text((left + 60, 2), "solve rate", fill=(20, 150, 60))
    steps = np.array([float(p["env_steps"]) for p in progress])
    if len(steps) >= 1:
        total = max(float(progress[-1].get("total_steps") or steps[-1]), 1.0)
        returns = np.array([float(p["mean_return"]) for p in progress])
        returns = np.where(np.isfinite(returns), returns, 0.0)
        solve = np.clip(np.nan_to_num(np.array([float(p["solve_rate"]) for p in progress])), 0.0, 1.0)
        lo, hi = float(returns.min()), float(returns.max())
        scaled = (returns - lo) / (hi - lo) if hi > lo else np.full_like(returns, 0.5)
        xs = left + (right - left) * steps / total
        for values, colour in ((scaled, (30, 80, 220)), (solve, (20, 150, 60))):
            ys = bottom - (bottom - top) * values
            points = list(zip(xs.tolist(), ys.tolist(), strict=True))
            if len(points) == 1:
                points = points * 2
            pen.line(points, fill=colour, width=2)
    return np.asarray(image)
