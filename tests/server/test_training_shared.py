"""Two servers on one PostgreSQL gallery share the training queue (issue 34; server.agents.shared_pool), through
their tabs (headless viser client, fake training worker): a run asked for in a tab on A while A's only worker is
busy is trained by B's worker, and the tab on A shows its queue position, its progress, "Training done" with the
specialist it can watch, or "Training cancelled." after its Cancel training; the author's specialist attached on A
is offered by B. Skipped without KINETIX_TEST_POSTGRES_URL (.ci/setup-postgres.sh)."""

from __future__ import annotations

import pytest
from fake_editor import falling_win_spec
from fake_training import fake_train_worker

from kinetix.formats import build
from kinetix.levels import to_document
from server.play.gallery_tab import GalleryLink
from tests.gallery.conftest import pg_schema_url  # noqa: F401  (a fresh PostgreSQL schema)
from tests.server.conftest import running_app, session_of, wait_until

FAKE_TRAINING = {"release": "unset"}


@pytest.fixture
def two_apps(pg_schema_url, tmp_path):  # noqa: F811
    FAKE_TRAINING["release"] = str(tmp_path / "release")
    settings = {"gallery": True, "db": pg_schema_url, "warm_sizes": (), "train_worker": fake_train_worker,
                "train_options": FAKE_TRAINING, "max_training_runs": 1}
    with running_app(data=tmp_path / "a", **settings) as a, running_app(data=tmp_path / "b", **settings) as b:
        yield a, b


def _status(client) -> str:
    return "\n".join(e.get("_markdown", "") for e in client.gui().values() if e["type"] == "GuiMarkdownMessage")


def test_a_tab_on_a_sees_its_run_trained_on_b_and_cancels_it(two_apps, make_client, tmp_path):
    a, b = two_apps
    assert type(a.training).__name__ == type(b.training).__name__ == "SharedTrainingPool"
    level_id, token = a.store.create_level("the author's level", to_document(build(falling_win_spec())))
    author_client = make_client(a)
    author, _ = session_of(a, author_client, 60.0)
    author.author_token = token
    GalleryLink(a.store).open(author, level_id)
    author_job = a.agents.train(author, steps=4000, options={"release": str(tmp_path / "release-author")})
    assert author_job.state == "running" and author_job.process is not None, "A's worker takes it at once"

    client = make_client(a)
    session, _ = session_of(a, client, 60.0)
    client.click_button("Train on this level")  # A's worker is busy: B's takes this one
    wait_until(lambda: "Training: 75,000 / 100,000 steps" in _status(client), 60)  # the default steps
    job = a.agents.tab(session).job
    assert job.process is None and b.training._runs, "trained by B's worker"
    client.click_button("Cancel training")
    wait_until(lambda: "Training cancelled." in _status(client), 30)
    wait_until(lambda: not b.training._runs, 30)

    job = a.agents.train(session, steps=4000, options={"release": str(tmp_path / "release-tab")})
    wait_until(lambda: job.state == "running" and b.training._runs, 30)  # B again: A's worker is still busy
    (tmp_path / "release-tab").touch()
    wait_until(lambda: "Training done" in _status(client), 60)
    assert job.state == "done" and job.process is None
    label, path = a.agents.specialists(session)[0]
    assert label.startswith("this tab's specialist") and path == str(job.out_dir / "checkpoint")
    assert path.startswith(str(tmp_path / "a")) and (job.out_dir / "checkpoint" / "config.json").is_file(), \
        "the checkpoint trained on B is in A's agents folder"

    (tmp_path / "release-author").touch()
    assert author_job.settled.wait(60) and author_job.state == "done"
    rows = b.agents.level_agents.list(level_id)  # the author's specialist, attached on A, fetched by B
    assert len(rows) == 1 and str(rows[0]["path"]).startswith(str(tmp_path / "b")) and rows[0]["path"].is_dir()
