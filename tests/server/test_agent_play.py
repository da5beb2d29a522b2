"""Agents in the browser, through the headless viser client: Watch agent (button and gallery link), the HUD and
overlay, Race the agent (deterministic stand-in agents), Train on this level with a cheap fake worker (queue,
progress, cancel, attach), and one slow real training that attaches a specialist Watch agent then plays."""

from __future__ import annotations

import io
import json
import re
import threading
import time

import jax.numpy as jnp
import numpy as np
import pytest
from fake_editor import falling_win_spec
from fake_training import fake_train_worker
from PIL import Image
from viser_client import KeysSocket

from kinetix.agents.policy import Policy
from kinetix.formats import ThrusterSpec, build
from kinetix.levels import to_document
from kinetix.recording import read_recording
from server.agents.play import AgentRunner, _overlay_box, action_text
from server.agents.tab import BEST, NEWEST, AgentLink
from server.play.gallery_tab import GalleryLink
from tests.server.conftest import running_app, session_of, wait_until

FAKE_TRAINING = {"release": "unset"}  # replaced per test (the fake worker waits for this file)


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    data = tmp_path_factory.mktemp("data")
    with running_app(gallery=True, data=data, warm_sizes=("m",), max_sessions=6, train_worker=fake_train_worker,
                     train_options=FAKE_TRAINING) as app:
        yield app


def _wait(predicate, timeout=60.0):
    wait_until(predicate, timeout)


def _session(app, client):
    return session_of(app, client, 60.0)


def _thruster_fall_document() -> dict:
    """falling_win with a sideways thruster (binding 0) on the ball: doing nothing solves it at step 9; firing the
    thruster from the start makes the ball miss the goal until the time limit."""
    spec = falling_win_spec()
    ball = next(i for i, body in enumerate(spec.bodies) if body.path == "ball")
    spec.thrusters.append(ThrusterSpec(path="push", body=ball, anchor=(0.0, 0.0), angle=0.0, power=1.0, binding=0))
    return to_document(build(spec))


def _thrusting_policy() -> Policy:
    """A stand-in agent that always fires thruster 0 (value estimate 0.5)."""
    action = jnp.array([0, 0, 0, 0, 1, 0], jnp.int32)
    return Policy("thrust", "multi_discrete", None, lambda params, key, obs: (action, jnp.float32(0.5)),
                  signature=("test-thrust",))


def _status(client) -> str:
    texts = [e.get("_markdown", "") for e in client.gui().values() if e["type"] == "GuiMarkdownMessage"]
    return "\n".join(texts)


def test_watch_agent_from_the_gallery_link_plays_pushes_frames_and_records_an_agent_play(app, make_client):
    level_id, token = app.store.create_level("falling win", to_document(build(falling_win_spec())))
    client = make_client(app)
    session, nonce = _session(app, client)
    start = client.count()
    keys = KeysSocket(app.port, nonce, query=f"?level={level_id}&mode=agent", token=token)
    try:
        _wait(lambda: session.gallery_id == level_id)
        _wait(lambda: session.mode == "ended", timeout=180)  # the first watch may compile the general agent
        assert session._result == "solved"
        assert session.player == "agent:general"
        _wait(lambda: app.store.stats(level_id)["agent_plays"] == 1)
        stats = app.store.stats(level_id)
        assert stats["agent_solved"] == 1 and stats["human_plays"] == 0
        # A frame per agent step (9 steps; viser may drop a frame superseded before it was sent): the play was
        # rendered, not just simulated.
        _wait(lambda: len(client.frames(start)) >= 6)
    finally:
        keys.close()


def test_the_watch_agent_button_shows_actions_per_binding_and_the_value(app, make_client):
    client = make_client(app)
    session, _ = _session(app, client)
    session.open_level(json.dumps(_thruster_fall_document()).encode(), "thrust.json")
    start = client.count()
    client.click_button("Watch agent")
    _wait(lambda: session.controller is not None and session.controller.runner.action is not None, timeout=180)
    assert client.wait_frame(start, timeout=30)
    _wait(lambda: session.controller is None or session.controller._scene is not None)
    hud = session.hud()
    # e.g. "PLAY  agent:general  step 3  0.10 s  T0 on  V +0.17": the level's one control, thruster 0, only
    assert re.search(r"  T0 (on|off)  V [+-]\d+\.\d\d", hud), hud
    assert "M0" not in hud and "T1" not in hud, hud
    assert "agent:general" in hud
    _wait(lambda: "Watching **general**" in _status(client))
    session.stop()
    assert session.controller is None and session.mode == "edit"


def test_action_text_and_overlay_box():
    assert action_text(np.array([0, 1, 2, 0, 1, 0])) == "M0 0 M1 + M2 - M3 0 T0 on T1 off"
    assert action_text(np.array([0, 1, 2, 0, 1, 0]), ({2, 1}, {0})) == "M1 + M2 - T0 on"
    assert action_text(np.array([0, 1, 2, 0, 1, 0]), (set(), set())) == "(no controls)"
    runner = AgentRunner("noop", build(falling_win_spec()).size)
    frame = np.full((240, 320, 3), 200, np.uint8)
    assert np.array_equal(_overlay_box(frame, runner, "agent"), frame), "no action yet: nothing drawn"
    runner.action, runner.value = np.array([0, 1, 2, 0, 1, 0], np.int32), 0.25
    drawn = _overlay_box(frame, runner, "agent")
    changed = np.argwhere((drawn != frame).any(axis=2))
    assert len(changed) > 0
    assert changed[:, 0].max() < 2 * 240 // 3 and changed[:, 1].max() < 2 * 320 // 3, "the box sits top left"


def _race(app, make_client, *, agent_policy, hold_thruster: bool):
    level_id, _ = app.store.create_level("race", _thruster_fall_document())
    client = make_client(app)
    session, nonce = _session(app, client)
    GalleryLink(app.store).open(session, level_id)
    keys = KeysSocket(app.port, nonce)
    try:
        race = app.agents.race(session, policy=agent_policy)
        assert session.mode == "ready", "a race waits for the human's first key"
        time.sleep(0.3)
        assert session._steps == 0 and race.agent.steps == 0, "neither side moved before the first key"
        start = client.count()
        keys.down("Digit1" if hold_thruster else "Space")  # the first control key starts the race and acts at once
        _wait(lambda: race.winner is not None, timeout=120)
        assert race.recorded.wait(30)
        _wait(lambda: len(client.frames(start)) > 0)
        return race, level_id, client, session
    finally:
        keys.close()


def test_race_human_wins_against_an_agent_that_misses_and_both_plays_are_recorded(app, make_client):
    race, level_id, client, session = _race(app, make_client, agent_policy=_thrusting_policy(), hold_thruster=False)
    assert race.winner == "human"
    assert race.human.result == "solved" and race.human.steps == 9
    assert race.agent.result is None and race.agent.steps == 9, "the agent stepped in lockstep"
    stats = app.store.stats(level_id)
    assert (stats["human_plays"], stats["human_solved"], stats["agent_plays"], stats["agent_solved"]) == (1, 1, 1, 0)
    # The race set the best time, and its recording is the best run (it used to be recorded without a file).
    assert stats["best_human_steps"] == 9 and stats["has_best_run"]
    best = read_recording(app.agents.runs.best_run_file(level_id), frames=False)
    assert best.num_steps == 9 and best.solved and best.metadata["player"] == "race"
    _wait(lambda: "You win!" in _status(client))
    _wait(lambda: session.mode == "ended")
    frame = session.render()
    assert frame.shape[1] == client.width, "one frame holds both halves"


def test_race_agent_wins_when_the_human_fires_the_thruster(app, make_client):
    from kinetix.agents.policy import load_policy
    from server.agents.play import observing_env

    noop = load_policy("noop", observing_env(build(falling_win_spec()).size))
    race, level_id, client, _ = _race(app, make_client, agent_policy=noop, hold_thruster=True)
    assert race.winner == "agent"
    assert race.agent.result == "solved" and race.human.result is None
    stats = app.store.stats(level_id)
    assert (stats["human_plays"], stats["human_solved"], stats["agent_plays"], stats["agent_solved"]) == (1, 0, 1, 1)
    _wait(lambda: "The agent wins!" in _status(client))


def test_training_queues_beyond_the_cap_shows_progress_attaches_and_cancels(app, make_client, tmp_path):
    FAKE_TRAINING["release"] = str(tmp_path / "release")
    level_id, token = app.store.create_level("train me", to_document(build(falling_win_spec())))
    first_client, second_client = make_client(app), make_client(app)
    first, _ = _session(app, first_client)
    second, _ = _session(app, second_client)
    first.author_token = token  # the level's author (the browser sends its token with the /keys hello)
    GalleryLink(app.store).open(first, level_id)
    first_job = app.agents.train(first, steps=4000)
    second_job = app.agents.train(second, steps=4000)  # a new, unsaved level: its specialist lives with the tab
    assert first_job.state == "running" and second_job.state == "queued"
    _wait(lambda: "position **1**" in _status(second_client))
    _wait(lambda: "Training: 3,000 / 4,000 steps" in _status(first_client))
    _wait(lambda: first_client.find_gui("Training")["visible"])  # the learning curve is shown
    with pytest.raises(ValueError, match="already training"):
        app.agents.train(first, steps=4000)
    (tmp_path / "release").touch()
    assert first_job.settled.wait(60)  # finished and its specialist attached
    assert first_job.state == "done"
    rows = app.agents.level_agents.list(level_id)
    assert len(rows) == 1 and rows[0]["solve_rate"] == 0.75 and rows[0]["path"].is_dir()
    assert app.agents.resolve(first, NEWEST)[1] == str(rows[0]["path"])
    assert app.agents.resolve(first, BEST)[1] == str(rows[0]["path"]), "the default prefers the level's specialist"
    assert app.agents.resolve(second, BEST) == ("general", "general"), "... and falls back to the general agent"
    _wait(lambda: "Training done" in _status(first_client))
    # The second run started once the first finished; it finishes at once (the release file exists) and stays
    # with its tab, since its level is not in the gallery.
    assert second_job.settled.wait(60)
    assert second_job.state == "done"
    assert app.agents.specialists(second)[0][0].startswith("this tab's specialist")
    assert app.agents.level_agents.list(level_id) == rows
    # Saving the second tab's level to the gallery attaches its specialist there for good.
    run_dir = second_job.out_dir
    saved_id = GalleryLink(app.store).save(second, "saved after training")
    labels = [label for label, _ in app.agents.specialists(second)]
    assert not any(label.startswith("this tab's") for label in labels)
    adopted = app.agents.level_agents.list(saved_id)
    assert len(adopted) == 1 and adopted[0]["path"] == run_dir / "checkpoint" and adopted[0]["solve_rate"] == 0.75
    second_client.close()
    _wait(lambda tab=second: tab.closed)
    del second
    import gc

    gc.collect()
    assert run_dir.is_dir(), "an adopted specialist outlives its tab"


def test_cancel_training_from_the_tab(app, make_client, tmp_path):
    FAKE_TRAINING["release"] = str(tmp_path / "never")
    client = make_client(app)
    session, _ = _session(app, client)
    client.click_button("Train on this level")
    _wait(lambda: app.agents.tab(session).job is not None and len(app.agents.tab(session).job.progress) == 3)
    job = app.agents.tab(session).job
    client.click_button("Cancel training")
    assert job.settled.wait(60)
    assert job.state == "cancelled" and not job.out_dir.exists()
    _wait(lambda: "Training cancelled." in _status(client))


def test_while_the_agent_loads_the_canvas_shows_the_level_and_says_so(app, make_client, monkeypatch):
    """Reading and compiling an agent can take a minute: the tab keeps drawing its level, with "loading agent ..." on
    it (issue 37), until the play starts; a load that fails takes the words away again."""
    loading, release = threading.Event(), threading.Event()
    warm = AgentRunner.warm

    def slow_warm(runner, state):
        loading.set()
        assert release.wait(60)
        if runner.label == "noop":
            raise RuntimeError("this agent does not load")
        warm(runner, state)

    monkeypatch.setattr(AgentRunner, "warm", slow_warm)
    client = make_client(app)
    session, _ = _session(app, client)
    session.open_level(json.dumps(to_document(build(falling_win_spec()))).encode(), "fall.json")
    start = client.count()
    worker = threading.Thread(target=app.agents.watch, args=(session, "random"), daemon=True)
    worker.start()
    assert loading.wait(30)
    assert session.mode == "edit" and (session._status or "").startswith("loading agent random")

    def words_over_the_level(jpeg: bytes) -> bool:
        rgb = np.asarray(Image.open(io.BytesIO(jpeg))).astype(int)
        ink = (rgb[..., 0] - rgb[..., 1:].max(axis=2) > 60) & (rgb[..., 0] < 235)  # the message's dark red, blended
        ball = np.abs(rgb - (0, 204, 0)).sum(axis=2) < 60
        return ink.sum() > 50 and ball.sum() > 100

    _wait(lambda: any(words_over_the_level(jpeg) for jpeg in client.frames(start)), timeout=30)
    release.set()
    worker.join(60)
    _wait(lambda: session.player == "agent:random")
    assert session._status is None
    session.stop()

    release.clear()
    loading.clear()
    failing = threading.Thread(target=app.agents._guarded, args=(session, app.agents.watch, session, "noop"),
                               daemon=True)
    failing.start()
    assert loading.wait(30) and session._status.startswith("loading agent noop")
    release.set()
    failing.join(60)
    assert session._status is None and session.mode == "edit"
    _wait(lambda: "this agent does not load" in _status(client))


def test_watch_refuses_a_missing_specialist_with_a_message(app, make_client):
    client = make_client(app)
    session, _ = _session(app, client)
    app.agents.tab(session).choice.value = NEWEST
    client.click_button("Watch agent")
    _wait(lambda: "has no specialist yet" in _status(client))
    assert session.mode == "edit"


@pytest.mark.slow
def test_a_tiny_real_training_attaches_a_specialist_that_watch_agent_plays(app, make_client):
    from server.agents.training import TrainingPool

    level_id, token = app.store.create_level("tiny training", to_document(build(falling_win_spec())))
    client = make_client(app)
    session, _ = _session(app, client)
    session.author_token = token
    GalleryLink(app.store).open(session, level_id)
    pool = TrainingPool(max_running=1)  # the real worker: kinetix.agents.train_agent in a spawned process
    link = AgentLink(store=app.store, agents_dir=app.agents.agents_dir, pool=pool,
                     train_options={"config": {"num_envs": 8, "num_steps": 32, "updates_per_call": 2}})
    try:
        job = link.train(session, steps=2048)
        assert job.settled.wait(900)
        assert job.state == "done", job.error
        assert len(job.progress) == 8 and job.progress[-1]["env_steps"] == 2048
        assert [p["env_steps"] for p in job.progress] == sorted(p["env_steps"] for p in job.progress)
        rows = link.level_agents.list(level_id)
        assert len(rows) == 1 and rows[0]["steps"] == 2048
        assert str(rows[0]["path"]).startswith(str(app.agents.agents_dir))
        controller = link.watch(session, NEWEST)
        assert controller.runner.spec == str(rows[0]["path"])
        _wait(lambda: session.mode == "ended", timeout=120)
        _wait(lambda: app.store.stats(level_id)["agent_plays"] == 1)
    finally:
        pool.close()


def test_warm_up_compiles_the_agent_function_for_each_size_class_once():
    from server.agents import play as agent_play

    before = {k for k in agent_play._FNS if k[0] == ("noop", "multi_discrete")}
    agent_play.warm_in_background(("s",), spec="noop").join(timeout=300)
    warmed = {k for k in agent_play._FNS if k[0] == ("noop", "multi_discrete")}
    assert any(k[1] == "s" for k in warmed)
    runner = AgentRunner("noop", build(falling_win_spec()).size)  # another runner of the same agent and size ...
    agent_play.warm_in_background(("m",), spec="noop").join(timeout=300)
    assert runner._fn is agent_play.step_fn(runner.policy, build(falling_win_spec()).size)  # ... shares its function
    assert len({k for k in agent_play._FNS if k[0] == ("noop", "multi_discrete")} - before) <= 2


def test_the_gallery_cards_watch_agent_link_opens_agent_mode():
    from pathlib import Path

    static = Path(__file__).resolve().parents[2] / "static"
    card = (static / "gallery.html").read_text()
    watch = next(line for line in card.splitlines() if "watch" in line)
    assert "<a " in watch and "disabled" not in watch
    assert '.watch").href = `./?level=${id}&mode=agent`' in (static / "gallery.js").read_text()  # relative: --root-path


def test_training_refuses_bad_step_counts(app, make_client):
    client = make_client(app)
    session, _ = _session(app, client)
    for steps in (0, 10**9):
        with pytest.raises(ValueError, match="training steps must be between"):
            app.agents.train(session, steps=steps)
    assert app.agents.tab(session).job is None


def test_a_closed_tabs_run_on_an_unsaved_level_is_cancelled(app, make_client, tmp_path):
    FAKE_TRAINING["release"] = str(tmp_path / "release")
    level_id, token = app.store.create_level("keeps training", to_document(build(falling_win_spec())))
    keeper, leaver = make_client(app), make_client(app)
    kept, _ = _session(app, keeper)
    left, _ = _session(app, leaver)
    kept.author_token = token
    GalleryLink(app.store).open(kept, level_id)
    kept_job = app.agents.train(kept, steps=4000)
    left_job = app.agents.train(left, steps=4000)  # unsaved level, queued behind the first
    assert left_job.state == "queued"
    leaver.close()
    _wait(lambda: left.closed)
    (tmp_path / "release").touch()
    assert kept_job.settled.wait(60) and left_job.settled.wait(60)
    assert kept_job.state == "done", "its author's run goes on: its specialist is attached for everyone"
    assert left_job.state == "cancelled" and not left_job.out_dir.exists()
    assert len(app.agents.level_agents.list(level_id)) == 1


def test_a_tab_specialist_is_deleted_with_its_tab(app, make_client, tmp_path):
    import gc

    FAKE_TRAINING["release"] = str(tmp_path / "release")
    (tmp_path / "release").touch()
    client = make_client(app)
    session, _ = _session(app, client)
    job = app.agents.train(session, steps=4000)
    assert job.settled.wait(60)
    assert job.state == "done" and app.agents.specialists(session)[0][1] == str(job.out_dir / "checkpoint")
    client.close()
    _wait(lambda tab=session: tab.closed)
    del session
    deadline = time.monotonic() + 30
    while job.out_dir.exists() and time.monotonic() < deadline:
        gc.collect()
        time.sleep(0.1)
    assert not job.out_dir.exists(), "nothing outlives the tab that owned it"


def test_a_specialist_attaches_to_a_level_whose_id_starts_with_a_dash(app, make_client, tmp_path):
    from sqlalchemy import text

    FAKE_TRAINING["release"] = str(tmp_path / "release")
    (tmp_path / "release").touch()
    source, token = app.store.create_level("dash", to_document(build(falling_win_spec())))
    with app.store._write() as conn:  # gallery ids are url-safe base64: '-' and '_' can come first
        conn.execute(text("INSERT INTO levels (id, name, description, author_id, created, updated, parent_id, size, "
                          "level_json, thumbnail) SELECT '-dash-first', name, description, author_id, created, "
                          "updated, NULL, size, level_json, thumbnail FROM levels WHERE id = :src"), {"src": source})
    client = make_client(app)
    session, _ = _session(app, client)
    session.author_token = token
    GalleryLink(app.store).open(session, "-dash-first")
    job = app.agents.train(session, steps=4000)
    assert job.settled.wait(60) and job.state == "done"
    assert len(app.agents.level_agents.list("-dash-first")) == 1


def test_a_project_level_shown_unchanged_is_raced_by_its_shipped_specialist(app, make_client, tmp_path):
    """A project level opened as a file gets the specialist shipped for it (server.agents.project) as "best", behind
    no other specialist; once edited it is another level and falls back to the general agent."""
    from server.agents.project import REPO_LEVELS, ProjectSpecialists

    shipped = tmp_path / "specialists" / "car_right"
    shipped.mkdir(parents=True)
    (shipped / "config.json").write_text("{}")  # resolve() only names the directory; nothing is loaded here
    client = make_client(app)
    session, _ = _session(app, client)
    saved = app.agents.project
    app.agents.project = ProjectSpecialists(tmp_path / "specialists", REPO_LEVELS)
    try:
        session.open_level((REPO_LEVELS / "car_right.json").read_bytes(), "car_right.json")
        assert app.agents.resolve(session, BEST) == ("project specialist (car_right)", str(shipped))
        app.agents.refresh_choices(session)
        assert "project specialist (car_right)" in app.agents.tab(session).choice.options
        _wait(lambda: app.store.counts()["levels"] >= 21)  # the gallery seeded from levels/
        GalleryLink(app.store).open(session, "car-right")  # the gallery's copy of it is the same level
        assert app.agents.resolve(session, BEST) == ("project specialist (car_right)", str(shipped))
        session.open_level((REPO_LEVELS / "car_ramp.json").read_bytes(), "car_ramp.json")
        assert app.agents.resolve(session, BEST) == ("general", "general"), "no specialist shipped for car_ramp"
        session.open_level((REPO_LEVELS / "car_right.json").read_bytes(), "car_right.json")
        document = json.loads(session.editor.export("ours"))
        document["bodies"][-1]["friction"] = 0.123  # any edit makes it another level
        session.open_level(json.dumps(document).encode(), "car_right.json")
        assert app.agents.resolve(session, BEST) == ("general", "general")
    finally:
        app.agents.project = saved
