"""In real headless Chromium: a level's best run, from the gallery card's "Watch best run" to frames changing in the
editor tab (`/?level=<id>&mode=replay`)."""

from __future__ import annotations

import time

import pytest
from viser_client import KeysSocket, ViserTestClient, session_nonce

from kinetix.formats import build
from kinetix.levels import to_document
from tests.e2e.conftest import Tab, wait_js
from tests.server.conftest import running_app, wait_until
from tests.server.fake_editor import falling_win_spec

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    folder = tmp_path_factory.mktemp("replay-e2e")
    with running_app(gallery=True, data=folder / "data", warm_sizes=("m",)) as app:
        yield app


def _wait(predicate, timeout=30.0):
    wait_until(predicate, timeout)


def _solve(app, level_id: str) -> None:
    """A protocol-level tab plays the level to its win, so the gallery keeps the run."""
    client = ViserTestClient(app.viser.get_port(), token=app.relay_token)
    try:
        nonce = session_nonce(client)
        keys = KeysSocket(app.port, nonce, query=f"?level={level_id}&mode=play")
        _wait(lambda: app.manager.session_by_nonce(nonce).mode == "ready")  # it waits for the first key
        keys.down("Space")
        _wait(lambda: app.store.stats(level_id)["has_best_run"], timeout=60)
        keys.close()
    finally:
        client.close()


def test_watch_best_run_opens_the_replay_and_its_frames_change(browser, app):
    level_id, _ = app.store.create_level("E2E replay", to_document(build(falling_win_spec())))
    _solve(app, level_id)
    tab = Tab(browser, app, 800, 600)
    try:
        gallery = tab.context.new_page()
        gallery.on("request", lambda request: tab.requests.append(request.url))
        gallery.goto(app.url + "gallery")
        card = gallery.locator("article.card", has_text="E2E replay")
        card.wait_for(timeout=30_000)
        button = card.locator("button.best-run")
        assert button.is_enabled()
        other = gallery.locator("article.card").filter(has_not_text="E2E replay").first
        assert other.locator("button.best-run").is_disabled(), "levels without a recorded solve: disabled"

        button.click()
        # keys.js adds &websocket=; 60 s as below: the server may still be compiling on a cold cache
        gallery.wait_for_url(f"**/?level={level_id}&mode=replay*", timeout=60_000)
        wait_js(gallery, "window.__kinetixKeys && window.__kinetixKeys.ready()")
        session = app.manager.session_by_nonce(gallery.get_attribute("#kinetix-session", "data-nonce"))
        _wait(lambda: session.mode == "replay" and session.replay is not None)
        replay = session.replay
        _wait(lambda: replay.frames_pushed >= 2)  # it plays on its own
        # Then the timeline: the start and the end of the run look different in the page.
        replay.set_playing(False)
        replay.seek(-1)
        _wait(lambda: replay.shown_step == -1)
        time.sleep(0.5)
        first = gallery.screenshot(timeout=60_000)
        # The slider (named by its label) takes arrow keys when it has the focus; its value counts steps done.
        slider = gallery.get_by_role("slider", name="Replay step")
        slider.focus()
        gallery.keyboard.press("ArrowRight")
        _wait(lambda: replay.shown_step == 0)
        wait_js(gallery, "document.querySelector('[role=slider]').getAttribute('aria-valuenow') === '1'")
        assert slider.get_attribute("aria-valuemax") == str(replay.last + 1)
        replay.seek(replay.last)
        _wait(lambda: replay.shown_step == replay.last)
        time.sleep(0.5)
        last = gallery.screenshot(timeout=60_000)
        assert first != last, "the replayed frames changed in the page"
        tab.assert_local_only()
    finally:
        tab.close()


def test_keyboard_play_then_download_recording_gives_the_browser_a_valid_file(browser, app):
    from kinetix.recording import read_recording, verify

    level_id, _ = app.store.create_level("E2E download", to_document(build(falling_win_spec())))
    tab = Tab(browser, app, 1280, 800)
    try:
        page = tab.page
        page.goto(app.url + f"?level={level_id}")
        wait_js(page, "window.__kinetixKeys && window.__kinetixKeys.ready()")
        session = app.manager.session_by_nonce(page.get_attribute("#kinetix-session", "data-nonce"))
        _wait(lambda: session.gallery_id == level_id)
        page.mouse.click(900, 400)  # focus the page
        page.keyboard.press("Space")
        _wait(lambda: session.mode == "ended")  # the ball falls onto the goal
        with page.expect_download(timeout=60_000) as download:
            page.get_by_role("button", name="Download recording", exact=True).click()
        path = download.value.path()
        assert download.value.suggested_filename.endswith(".mcap")
        recording = read_recording(path)
        assert recording.solved and recording.metadata["level_id"] == level_id
        assert verify(recording).ok
        tab.assert_local_only()
    finally:
        tab.close()
