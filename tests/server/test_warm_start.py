"""The server answers before it compiles (issue 29): with the play step's compile held back, GET / answers, a tab
opens and says "preparing the simulation" with the progress, and a Play asked for meanwhile starts once the step
is compiled instead of failing."""

from __future__ import annotations

import threading
import urllib.request

import pytest
from fake_editor import FakeEditor, falling_win_spec

from server.play import steps
from server.play.warmup import PREPARING, WarmUp
from tests.server.conftest import running_app, session_of, wait_until


@pytest.fixture
def held_compile(monkeypatch):
    """The warm-up's compile of a play step waits for this event (set it to let the compile go on)."""
    gate = threading.Event()
    real = steps.warm_up

    def slow_warm_up(*args, **kwargs):
        gate.wait(timeout=120)
        real(*args, **kwargs)

    monkeypatch.setattr(steps, "warm_up", slow_warm_up)
    yield gate
    gate.set()  # never leave the server's shutdown waiting for the compile


def test_the_page_answers_and_the_tab_shows_progress_before_the_step_compiles(held_compile, make_client):
    editor = lambda level=None, size="m": FakeEditor(falling_win_spec(), size=size)  # noqa: E731
    with running_app(wait_warm=False, warm_sizes=("m",), editor_factory=editor) as app:
        with urllib.request.urlopen(app.url, timeout=10) as response:
            assert response.status == 200
        assert not app.warmup.ready("m")  # the page answered while the compile was held back
        client = make_client(app)
        session, _ = session_of(app, client)
        assert f"{PREPARING}: compiling size m: 1 of 1" in session.hud()
        assert session.frames_sent >= 1  # the tab drew its level, not a blank page

        session.toggle_play()  # Play before the step is ready: it waits, it does not fail
        assert session.mode == "edit" and PREPARING in session._message
        held_compile.set()
        wait_until(lambda: session.mode == "play", timeout=300)
        assert session._message is None
        wait_until(lambda: app.warmup.finished)  # the play starts as soon as its size is ready, the rest may follow
        session.stop()
        assert PREPARING not in session.hud() and "Space: play" in session.hud()  # the edit view, ready
        client.close()


def test_escape_while_preparing_cancels_the_play(held_compile, make_client):
    editor = lambda level=None, size="m": FakeEditor(falling_win_spec(), size=size)  # noqa: E731
    with running_app(wait_warm=False, warm_sizes=("m",), editor_factory=editor) as app:
        client = make_client(app)
        session, _ = session_of(app, client)
        session.toggle_play()
        session.stop()  # Esc / Edit
        held_compile.set()
        assert app.wait_until_warm(timeout=300)
        assert session.mode == "edit" and session._message is None
        client.close()


def test_progress_counts_every_task_in_order():
    order = []
    warm = WarmUp(("s", "m"), batches=True, agent=lambda sizes: order.append(("agent", sizes)))
    warm._compile = lambda kind, size, real=warm._compile: order.append((kind, size)) if kind != "agent" \
        else real(kind, size)
    seen = []
    warm.on_progress(lambda: seen.append(warm.progress()))
    started = []
    assert warm.when_ready("m", lambda: started.append(warm.ready("m")))
    assert warm.progress() == "compiling size s: 1 of 4"
    warm.start().join(timeout=10)
    assert order == [("size", "s"), ("size", "m"), ("batches", ""), ("agent", ("s", "m"))]
    assert seen[:4] == ["compiling size s: 1 of 4", "compiling size m: 2 of 4", "compiling the batched steps: 3 of 4",
                        "compiling the agent: 4 of 4"]
    assert seen[-1] is None and started == [True]
    assert warm.ready("xl")  # a size class not warmed at start compiles on its first play, as before
    assert not warm.when_ready("m", lambda: None)  # already ready: nothing to wait for


def test_work_prepended_runs_first_and_is_named_in_the_progress():
    warm = WarmUp(("s",), batches=False)
    warm._compile = lambda kind, size, real=warm._compile: real(kind, size) if kind == "call" else None
    seen = []
    warm.prepend("the gallery's levels", lambda: seen.append(warm.progress()))
    warm.start().join(timeout=10)
    assert seen == ["preparing the gallery's levels: 1 of 2"] and warm.finished and warm.ready("s")


def test_a_cancelled_warm_up_skips_what_it_has_not_started():
    ran = []
    warm = WarmUp(("s", "m"), batches=True)
    warm._compile = lambda kind, size: (ran.append((kind, size)), warm.cancel())
    then = []
    warm.start(then=lambda: then.append(1)).join(timeout=10)
    assert ran == [("size", "s")] and warm.finished and then == [1]


def test_the_gallery_api_answers_503_until_its_levels_are_seeded_never_an_empty_list(monkeypatch):
    """A new gallery is seeded by the warm-up after the server answers (issue 34): meanwhile the API says it is
    preparing (503, Retry-After) instead of listing nothing; afterwards the project's levels are there."""
    import json
    import urllib.error

    from server.gallery.store import Store

    gate = threading.Event()
    real = Store.seed

    def held_seed(self, folder):
        gate.wait(timeout=120)
        return real(self, folder)

    monkeypatch.setattr(Store, "seed", held_seed)
    with running_app(wait_warm=False, warm_sizes=(), gallery=True) as app:
        try:
            with pytest.raises(urllib.error.HTTPError) as preparing:
                urllib.request.urlopen(f"http://127.0.0.1:{app.port}/api/levels", timeout=30)
            assert preparing.value.code == 503 and preparing.value.headers["Retry-After"] == "2"
            assert "being prepared" in json.loads(preparing.value.read())["detail"]
        finally:
            gate.set()
        wait_until(lambda: app.warmup.wait(0.1, sizes_only=False), timeout=120)
        with urllib.request.urlopen(f"http://127.0.0.1:{app.port}/api/levels", timeout=30) as answer:
            assert json.loads(answer.read())["items"], "the project's levels"
