"""Training and agents belong to someone (issue 26 §2), through the tab (headless viser client, fake training
worker): only the level's author attaches a specialist to it, anyone else's stays with their tab or their own copy;
closing a tab ends its run at once (worker process gone) unless its author's run is bound to their level; one
person's runs are limited and the queue takes turns between people, with clear messages in the tab."""

from __future__ import annotations

import pytest
from fake_editor import falling_win_spec
from fake_training import fake_train_worker

from kinetix.formats import build
from kinetix.levels import to_document
from server.play.gallery_tab import GalleryLink
from tests.server.conftest import running_app, session_of, wait_until

FAKE_TRAINING = {"release": "unset"}  # replaced per test (the fake worker waits for this file)


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    data = tmp_path_factory.mktemp("data")
    with running_app(gallery=True, data=data, warm_sizes=(), max_sessions=6, train_worker=fake_train_worker,
                     train_options=FAKE_TRAINING, max_training_runs=1) as app:
        yield app


@pytest.fixture
def release(app, tmp_path):
    """The file that lets the fake workers finish; every test starts with an idle pool."""
    wait_until(lambda: not app.training.jobs(), 60)
    FAKE_TRAINING["release"] = str(tmp_path / "release")
    yield tmp_path / "release"
    for job in app.training.jobs():
        app.training.cancel(job)


def _tab(app, make_client, *, token=None, level_id=None):
    client = make_client(app)
    session, _ = session_of(app, client, 60.0)
    session.author_token = token  # as the browser's /keys hello sets it
    if level_id is not None:
        GalleryLink(app.store).open(session, level_id)
    return client, session


def _status(client) -> str:
    return "\n".join(e.get("_markdown", "") for e in client.gui().values() if e["type"] == "GuiMarkdownMessage")


def _level(app, name):
    return app.store.create_level(name, to_document(build(falling_win_spec())))


def test_a_non_authors_specialist_stays_with_their_tab_or_their_own_copy(app, make_client, release):
    release.touch()
    level_id, _ = _level(app, "someone's level")
    _, stranger_token = _level(app, "the stranger's own level")  # a known author, but not this level's
    client, session = _tab(app, make_client, token=stranger_token, level_id=level_id)
    job = app.agents.train(session, steps=4000)
    assert job.settled.wait(60) and job.state == "done"
    assert app.agents.level_agents.list(level_id) == [], "a non-author's run is never attached to the level"
    wait_until(lambda: "only the level's author can attach" in _status(client), 30)
    label, path = app.agents.specialists(session)[0]
    assert label.startswith("this tab's specialist") and path == str(job.out_dir / "checkpoint")
    _, viewer = _tab(app, make_client, level_id=level_id)
    assert app.agents.specialists(viewer) == [], "another tab on the level does not see it"
    copy_id = GalleryLink(app.store).save(session, "my own copy")  # saved with the stranger's own token
    assert session.author_token == stranger_token
    adopted = app.agents.level_agents.list(copy_id)
    assert len(adopted) == 0  # attached on the next read of the agent list (e.g. a button press) ...
    app.agents.specialists(session)
    adopted = app.agents.level_agents.list(copy_id)
    assert [row["path"] for row in adopted] == [job.out_dir / "checkpoint"], "... to the copy the stranger owns"
    GalleryLink(app.store).open(session, level_id)
    app.agents.specialists(session)
    assert app.agents.level_agents.list(level_id) == []


def test_closing_the_tab_ends_its_run_at_once(app, make_client, release):
    client, session = _tab(app, make_client)  # a new level: the run belongs to the tab
    client.click_button("Train on this level")
    wait_until(lambda: app.agents.tab(session).job is not None and len(app.agents.tab(session).job.progress) == 3,
               60)
    job = app.agents.tab(session).job
    process = job.process
    assert process.is_alive()
    wait_until(lambda: "It stops if you close this tab." in _status(client), 30)
    client.close()  # the fake worker reports nothing more: no progress report is needed to notice
    wait_until(lambda: session.closed, 30)
    assert job.settled.wait(30)
    assert job.state == "cancelled" and not process.is_alive() and process.exitcode is not None
    assert not job.out_dir.exists(), "nothing of the run is kept"
    assert app.training.jobs() == []


def test_the_authors_bound_run_survives_the_tab_close_and_is_attached(app, make_client, release):
    level_id, token = _level(app, "the author's level")
    author_client, author = _tab(app, make_client, token=token, level_id=level_id)
    stranger_client, stranger = _tab(app, make_client, level_id=level_id)  # anonymous, same level
    author_job = app.agents.train(author, steps=4000)
    stranger_job = app.agents.train(stranger, steps=4000)
    assert author_job.state == "running" and stranger_job.state == "queued"
    wait_until(lambda: len(author_job.progress) == 3, 60)
    wait_until(lambda: "It goes on if you close this tab" in _status(author_client), 30)
    author_client.close()
    stranger_client.close()
    wait_until(lambda: author.closed and stranger.closed, 30)
    assert stranger_job.settled.wait(30) and stranger_job.state == "cancelled" and stranger_job.process is None
    assert author_job.state == "running" and author_job.process.is_alive(), "the author's run goes on"
    release.touch()
    assert author_job.settled.wait(60) and author_job.state == "done"
    rows = app.agents.level_agents.list(level_id)
    assert [row["path"] for row in rows] == [author_job.out_dir / "checkpoint"] and rows[0]["path"].is_dir()


def test_a_run_whose_level_the_tab_saved_as_its_own_survives_the_close(app, make_client, release):
    client, session = _tab(app, make_client)  # anonymous, a new level: the run starts as the tab's
    job = app.agents.train(session, steps=4000)
    wait_until(lambda: len(job.progress) == 3, 60)
    saved_id = GalleryLink(app.store).save(session, "saved while training")  # issues the tab an author token
    client.close()
    wait_until(lambda: session.closed, 30)
    assert job.state == "running" and job.process.is_alive()
    release.touch()
    assert job.settled.wait(60) and job.state == "done"
    assert [row["path"] for row in app.agents.level_agents.list(saved_id)] == [job.out_dir / "checkpoint"]


def test_one_persons_runs_are_limited_and_the_queue_takes_turns(app, make_client, release):
    _, token = _level(app, "an author's identity")
    tabs = [_tab(app, make_client, token=token) for _ in range(3)]  # one browser: its tabs share the token
    (first_client, first), (second_client, second), (third_client, third) = tabs
    first_job = app.agents.train(first, steps=4000)
    second_job = app.agents.train(second, steps=4000)
    assert first_job.state == "running" and second_job.state == "queued"
    wait_until(lambda: "it waits for your other run (at most 1 at a time per person)" in _status(second_client), 30)
    third_client.click_button("Train on this level")
    wait_until(lambda: "Cannot do that:" in _status(third_client), 30)
    assert "you already have 2 training runs going or waiting" in _status(third_client)
    assert app.agents.tab(third).job is None
    _, other = _tab(app, make_client)  # another person asks later, but goes before the first person's second run
    other_job = app.agents.train(other, steps=4000)
    assert [app.training.position(job) for job in (other_job, second_job)] == [1, 2]
    app.training.cancel(first_job)
    wait_until(lambda: other_job.state == "running", 30)
    assert second_job.state == "queued"
