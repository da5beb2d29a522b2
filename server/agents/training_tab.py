"""Training in a tab: Train on this level (bound to the gallery level the tab owns, else the tab's own run), its
progress bar and learning curve, Cancel training, and what becomes of a run and its specialists when the tab
closes (docs/agents.md, "Training belongs to someone"). AgentLink (server.agents.tab) inherits TabTraining.
"""

from __future__ import annotations

import dataclasses
import html
import json
import logging
import secrets
import shutil
import time
import weakref

import numpy as np
from PIL import Image, ImageDraw

from server.agents.training import TrainingJob

log = logging.getLogger("server.agents.tab")  # one log for the tab's agent folder

# The agent choices of a tab's Agent folder (besides each specialist by name); a finished run selects NEWEST.
GENERAL = "general"
NEWEST = "newest specialist"
BEST = "best: newest specialist, else general"
DEFAULT_TRAIN_STEPS = 100_000
MAX_TRAIN_STEPS = 10_000_000  # a tab cannot start a run of days by a typo
CURVE_SIZE = (300, 130)


class TabTraining:
    """Mixed into AgentLink: a tab's training runs."""

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
        return without_name(stored) == without_name(document)

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
            workers = pool.workers()  # this process's, or with a shared queue every process's
            why = (f"it waits for your other run (at most {pool.per_client} at a time per person)"
                   if pool.waits_for_own_run(job) else
                   f"at most {workers} run{'s' if workers != 1 else ''} at a time; "
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


@dataclasses.dataclass(eq=False)
class RunOwner:
    """Whose a tab's training run is: the gallery level it is bound to (attached when done; it outlives the tab)
    with the author token that owns that level, or no level (it belongs to the tab and ends with it)."""

    level_id: str | None = None
    token: str | None = None


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


def without_name(document: dict) -> dict:
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
